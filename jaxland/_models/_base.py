"""The model contract: what a landing model gives the integrators.

A model is an ``eqx.Module`` subclass of ``AbstractModel`` (as a diffrax solver subclasses
``AbstractSolver``): it has no parameters of its own (those are the ``Vehicle`` and the
``Scene``), only methods with typed inputs and outputs. The integrators in ``jaxland._solvers``
call nothing else, so a new model (a planar one, a leg with another buffer) implements these
methods and runs with every integrator that its capabilities allow:

- ``initial_state`` -> the model's state Module, with fields ``t`` [s], ``q`` and ``v``
  (generalised positions and velocities, any pytree), ``diss_rate`` (the accumulated
  ``RATE_CHANNELS`` [J]) and the constitutive memories;
- ``prepare`` -> the model's ``Derived`` Module: parameter-derived numbers computed once
  outside the time loop, and the switch ``Smoothing``;
- ``evaluate`` -> an ``Evaluation``: accelerations, the state with its memories advanced, the
  named outputs, the dissipation powers, the energy stores and the dissipation channels;
- ``drift`` -> positions from new velocities;
- ``kinetic_energy`` -> the ledger's kinetic energy at any velocities;
- ``oscillator`` -> the stiffest, lightest oscillator, from which each integrator states its
  stability limit.

Capabilities beyond the fixed-step methods are abstract mixins: ``AbstractImpulseModel`` (the
paper's discrete-impulse method needs one primary force) and ``AbstractODEModel`` (an adaptive
ODE solver needs the memories in rate form).
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from .._params import Vehicle
from .._scene import Scene


class Smoothing(eqx.Module):
    """Widths of the rounded force-law switches (``jaxland._laws._smooth``): 0 keeps the hard
    switches. Static: they choose code."""

    length_m: float = eqx.field(static=True, default=0.0)  # m: contact, unloading, stick/slip
    force_N: float = eqx.field(static=True, default=0.0)  # N: the strut's no-pull floor


class Evaluation(eqx.Module):
    """What a model computes at one state.

    ``stores`` and ``dissipated`` together are the energy ledger at this state, less the
    ``RATE_CHANNELS`` that the integrator accumulates from ``power``; their sum in the order
    written is the ledger's total, so the stores come first (kinetic, potential, elastic) and
    the dissipation channels after.
    """

    accel: PyTree[Array]  # generalised accelerations, shaped like the state's v
    state: eqx.Module  # the evaluated state with its memories advanced by their return maps
    record: dict[str, Array]  # named outputs (CSV columns; units in the names)
    power: Array  # (len(RATE_CHANNELS),) W, dissipation powers the integrator accumulates
    stores: dict[str, Array]  # J: kinetic_J, potential_J, elastic_*_J
    dissipated: dict[str, Array]  # J: diss_*_J given by the memories (not by a power)

    def ledger(self) -> Array:
        """Stores plus closed-form dissipation [J] (the rate channels excluded)."""
        return sum([*self.stores.values(), *self.dissipated.values()])


class Oscillator(eqx.Module):
    """The stiffest, lightest oscillator a model contains: what limits a fixed time step.

    A mass ``mass`` held by springs summing to ``stiffness``, damped by the strut
    (``strut_damping`` x ``strut_force``) and by the ground (``ground_damping`` x
    ``ground_force``): both dampers grow with the force they carry.
    """

    mass: Array  # kg
    stiffness: Array  # N/m
    strut_damping: Array  # s/m, damping force per unit strut force per unit velocity (D_b)
    strut_force: Array  # N
    ground_damping: Array  # s/m, the same for the ground (chi)
    ground_force: Array  # N


class AbstractModel(eqx.Module):
    """A landing model (see the module docstring for the contract).

    ``second_order`` (static; ``Verlet`` runs the model with it on): the evaluation keeps a
    step's second order where a first-order step does not need it. The implicit strut
    damping's free stroke rate then includes the kick of the strut's body attachment (the
    body's acceleration from the forces with the damping explicit), and the slip energy is a
    trapezoid of the tangential force before and after the slip (carried in the state's
    ``t_force``). Off (the default), a first-order method's code is unchanged."""

    second_order: bool = eqx.field(static=True, default=False)
    name: ClassVar[str]
    COLUMNS: ClassVar[tuple[str, ...]]  # trajectory columns in CSV order, units in the names
    RATE_CHANNELS: ClassVar[tuple[str, ...]]  # dissipation channels integrated from a power

    def apply_scene(self, vehicle: Vehicle, scene: Scene) -> Vehicle:
        """The vehicle as the scene changes it: honeycomb plateau scatter (both plateaus of
        each leg times ``plateau_scatter``), the friction override, and the mass scale (body
        mass and inertia)."""
        if scene.plateau_scale is not None:
            scale = self.plateau_scatter(scene.plateau_scale)
            hc = vehicle.honeycomb
            vehicle = eqx.tree_at(lambda v: (v.honeycomb.F1, v.honeycomb.F2), vehicle,
                                  (hc.F1 * scale, hc.F2 * scale))
        if scene.friction is not None:
            vehicle = eqx.tree_at(lambda v: v.ground.mu, vehicle, scene.friction)
        if scene.mass_scale is not None:
            s = scene.mass_scale
            vehicle = eqx.tree_at(lambda v: (v.m_body, v.I_xx, v.I_yy, v.I_zz), vehicle,
                                  (vehicle.m_body * s, vehicle.I_xx * s, vehicle.I_yy * s,
                                   vehicle.I_zz * s))
        return vehicle

    def plateau_scatter(self, plateau_scale: Array) -> Array:
        """The plateau-force scale the model's legs take from the scene's per-leg scale."""
        return plateau_scale

    @abc.abstractmethod
    def prepare(self, vehicle: Vehicle, scene: Scene, smoothing: Smoothing = Smoothing()):
        """Parameter-derived numbers for the step, computed once outside the time loop (XLA
        does not hoist divisions, roots and trigonometry out of it)."""

    @abc.abstractmethod
    def initial_state(self, vehicle: Vehicle, scene: Scene):
        """The state at t = 0."""

    @abc.abstractmethod
    def evaluate(self, vehicle: Vehicle, state, scene: Scene, derived, kick=None) -> Evaluation:
        """Forces and accelerations at ``state``. ``kick`` [s]: when given, the strut damping
        is implicit, evaluated at the stroke rate after a velocity kick of that length;
        ``None`` is explicit."""

    @abc.abstractmethod
    def kinetic_energy(self, vehicle: Vehicle, derived, v) -> Array:
        """Kinetic energy [J] at the velocities ``v`` (the ledger's ``kinetic_J``): diagonal
        in the velocities."""

    @abc.abstractmethod
    def drift(self, q, v, dt):
        """Positions after ``dt`` at the new velocities ``v``."""

    @abc.abstractmethod
    def energy_scale(self, vehicle: Vehicle, scene: Scene) -> Array:
        """Energy the landing has to absorb, generously bounded [J]: the ledger's scale."""

    @abc.abstractmethod
    def accel_record(self, accel) -> dict[str, Array]:
        """Named acceleration outputs [m/s^2]."""

    @abc.abstractmethod
    def peak_values(self, record: dict, accel) -> dict[str, Array]:
        """Quantities whose running maximum over every step is kept."""

    @abc.abstractmethod
    def contact_flag(self, record: dict) -> Array:
        """Some foot is on the ground."""

    @abc.abstractmethod
    def tipping(self, record: dict) -> Array:
        """The vehicle is tipping over (only counted after the first touchdown)."""

    def could_still_tip(self, vehicle: Vehicle, ev: Evaluation) -> Array:
        """At the state evaluated in ``ev``, an upright vehicle still has the energy to tip
        over, so a tip-over outcome taken there is not final (a model that cannot tip: never)."""
        return jnp.zeros((), bool)

    @abc.abstractmethod
    def final_summary(self, state, record: dict) -> dict[str, Array]:
        """Model-specific outcomes at the end of the landing."""

    def leg_mass(self, vehicle: Vehicle) -> Array:
        """Body mass one leg may have to stop [kg] (the quarter model: its share; a model whose
        legs can touch down one by one: the whole body)."""
        return vehicle.m_body

    def leg_max(self, x: Array) -> Array:
        """A per-leg summary value reduced to the landing's worst leg (identity for one leg)."""
        return x

    def oscillator(self, vehicle: Vehicle, honeycomb_force=None, normal_force=None,
                   bottomed: bool = False) -> Oscillator:
        """The foot (the lightest mass) held at once by the stiffest elastic element of the
        strut (k_b1, k_b3, the top-out stop, and k_bottom once the stack has bottomed out), the
        auxiliary struts, the ground in restitution (k / (1 - gamma)) and the tangential
        spring. Without forces given, both dampers carry the second plateau F2; after a run,
        pass the peak honeycomb and normal forces reached (and whether it bottomed out)."""
        hc, leg, gr = vehicle.honeycomb, vehicle.leg, vehicle.ground
        k_el = jnp.maximum(jnp.maximum(hc.k_b1, hc.k_b3), leg.k_topout)
        k_el = jnp.where(bottomed, jnp.maximum(k_el, hc.k_bottom), k_el)
        f_hc = hc.F2 if honeycomb_force is None else jnp.maximum(hc.F2, honeycomb_force)
        f_n = hc.F2 if normal_force is None else jnp.maximum(hc.F2, normal_force)
        return Oscillator(
            mass=jnp.minimum(vehicle.m_foot, vehicle.m_quarter),
            stiffness=k_el + leg.k_a + gr.k_r + gr.k_tan,
            strut_damping=leg.D_b, strut_force=f_hc, ground_damping=gr.chi, ground_force=f_n)


class AbstractImpulseModel(AbstractModel):
    """A model with one primary contact force, as the discrete-impulse method needs."""

    @abc.abstractmethod
    def impulse_step_force(self, record: dict) -> Array:
        """The force that sets the impulse step, dt = dI / F [N]."""


class AbstractODEModel(AbstractModel):
    """A model written as a continuous ODE y' = f(t, y), memories in rate form."""

    @abc.abstractmethod
    def ode_state(self, state) -> Array:
        """The state as one flat vector."""

    @abc.abstractmethod
    def from_ode(self, t, y):
        """The state from ``ode_state``'s vector at time ``t``."""

    @abc.abstractmethod
    def ode_rates(self, vehicle: Vehicle, t, y, scene: Scene, derived) -> Array:
        """dy/dt."""
