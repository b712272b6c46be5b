"""The fixed-step methods: symplectic Euler, with implicit strut damping, velocity Verlet, and
the one-evaluation leapfrog.

Each evaluates the model's forces, which also advances the constitutive memories (largest
crush, deepest pit, stick point) by their return maps, then kicks and drifts. For
x'' = -omega^2 x - c x' on the model's ``Oscillator`` (foot mass m, springs k, dampers
c = (D_b F_bh + chi F_n) / m), symplectic Euler is stable while dt^2 omega^2 + 2 dt c <= 4, i.e.
dt <= (sqrt(c^2 + 4 omega^2) - c) / omega^2 (2/omega without damping, 2/c without stiffness).
Taking the strut damping implicitly leaves only the (small) ground damping in c.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._models import Oscillator
from ._base import AbstractIntegrator
from ._loop import advance, kick, run_fixed


def _limit(osc: Oscillator, strut: bool):
    w2 = osc.stiffness / osc.mass
    c = ((osc.strut_damping * osc.strut_force if strut else 0.0)
         + osc.ground_damping * osc.ground_force) / osc.mass
    # (sqrt(c^2 + 4 w^2) - c) / w^2, written without its cancellation: where the damping
    # dominates (c^2 >> w^2) the difference rounds to 0, and an overflowing w^2 gives inf/inf
    return jnp.min(4.0 / (jnp.sqrt(c**2 + 4.0 * w2) + c))


class AbstractFixedStep(AbstractIntegrator):
    """A one-step method at fixed dt, run by ``jaxland._solvers._loop.run_fixed``."""

    @abc.abstractmethod
    def step(self, model, vehicle, s, scene, derived, dt):
        """``(next state, Evaluation at s)``."""

    def record_kick(self, dt):
        """The implicit-damping kick [s] the step applies to the forces at a state (``None``:
        explicit), so saved forces are the ones applied."""
        return None

    def start(self, ev0):
        """What the step carries from one step to the next, at the initial state, from that
        state's evaluation ``ev0`` without a kick (``None``: nothing; a method that reuses its
        last evaluation carries it)."""
        return None

    def step_carried(self, model, vehicle, s, scene, derived, dt, carried):
        """``(next state, (state, its Evaluation) for the bookkeeping, next carried)``."""
        s1, ev = self.step(model, vehicle, s, scene, derived, dt)
        return s1, (s, ev), carried

    def integrate(self, model, vehicle, scene, solver):
        return run_fixed(self, model, vehicle, scene, solver)


class Euler(AbstractFixedStep):
    """Symplectic (semi-implicit) Euler: v_{n+1} = v_n + dt a(q_n, v_n), q_{n+1} = q_n +
    dt v_{n+1}. First order, one evaluation per step. On the paper gear the strut damping sets
    its limit (1.3e-4 s, against 4.5e-4 s for the springs)."""

    name: ClassVar[str] = "euler"
    stability_reason: ClassVar[str] = "stiffest springs and the strut damping on the foot"

    def stable_step(self, osc):
        return _limit(osc, strut=True)

    def step(self, model, vehicle, s, scene, derived, dt):
        ev = model.evaluate(vehicle, s, scene, derived)
        v1 = kick(s.v, ev.accel, dt)
        return advance(ev.state, s, model.drift(s.q, v1, dt), v1, dt, dt * ev.power), ev


class EulerImplicit(Euler):
    """Symplectic Euler with the strut damping implicit (at the foot's new velocity, the body
    held): one evaluation per step, first order, stable to 2/omega of the springs."""

    name: ClassVar[str] = "euler_implicit"
    stability_reason: ClassVar[str] = ("stiffest springs on the foot; the strut damping is "
                                       "implicit")

    def stable_step(self, osc):
        return _limit(osc, strut=False)

    def record_kick(self, dt):
        return dt

    def step(self, model, vehicle, s, scene, derived, dt):
        ev = model.evaluate(vehicle, s, scene, derived, dt)
        v1 = kick(s.v, ev.accel, dt)
        return advance(ev.state, s, model.drift(s.q, v1, dt), v1, dt, dt * ev.power), ev


class Verlet(AbstractFixedStep):
    """Velocity Verlet (kick-drift-kick), second order where the forces are smooth, with the
    strut damping on a Crank-Nicolson split: the first half kick takes it implicitly (backward
    Euler over dt/2), the second explicitly from the half-step velocity, so a pure dashpot is
    damped by (1 - a)/(1 + a), a = c dt / 2 m: A-stable, and the stable step is 2/omega of the
    springs. Two evaluations per step."""

    name: ClassVar[str] = "verlet"
    stability_reason: ClassVar[str] = EulerImplicit.stability_reason

    def stable_step(self, osc):
        return _limit(osc, strut=False)

    def record_kick(self, dt):
        return 0.5 * dt

    def integrate(self, model, vehicle, scene, solver):
        """With the model's ``second_order`` evaluation (``AbstractModel``)."""
        return super().integrate(dataclasses.replace(model, second_order=True), vehicle, scene,
                                 solver)

    def step(self, model, vehicle, s, scene, derived, dt):
        h = 0.5 * dt
        ev = model.evaluate(vehicle, s, scene, derived, h)
        v_half = kick(s.v, ev.accel, h)
        q1 = model.drift(s.q, v_half, dt)
        s_half = _at_half(ev.state, q1, v_half)
        ev2 = model.evaluate(vehicle, s_half, scene, derived)
        v1 = kick(v_half, ev2.accel, h)
        return advance(ev2.state, s, q1, v1, dt, h * (ev.power + ev2.power)), ev


def _at_half(s_m, q1, v_half):
    return eqx.tree_at(lambda x: (x.q, x.v), s_m, (q1, v_half))


class Leapfrog(Verlet):
    """Kick-drift-kick with one evaluation per step: velocity Verlet whose end-of-step
    evaluation is also the next step's start (first same as last). That evaluation, at the new
    positions and the half-step velocity, takes the strut damping implicitly over the second
    half kick, so the strut's damping force is the one at the step's end velocity, and the next
    step's first half kick reuses it: a Crank-Nicolson split of the damping over each step
    (A-stable, the stable step is 2/omega of the springs, as Verlet's) that keeps second order
    at half of Verlet's evaluations. The ground damping and the gyroscopic torque are read at
    the half-step velocity, as in Verlet's second evaluation. The dissipation powers are booked
    as a trapezoid, the slip energy as Verlet books it (``AbstractModel.second_order``)."""

    name: ClassVar[str] = "leapfrog"  # Verlet's stable step, record kick and evaluation

    def start(self, ev0):
        return ev0.accel, ev0.power  # the first half kick's forces

    def step_carried(self, model, vehicle, s, scene, derived, dt, carried):
        acc, power = carried
        h = 0.5 * dt
        v_half = kick(s.v, acc, h)
        q1 = model.drift(s.q, v_half, dt)
        ev = model.evaluate(vehicle, _at_half(s, q1, v_half), scene, derived, h)
        v1 = kick(v_half, ev.accel, h)
        s1 = advance(ev.state, s, q1, v1, dt, h * (power + ev.power))
        # the bookkeeping reads the new state: its ledger with the kinetic energy at v1
        stores = dict(ev.stores, kinetic_J=model.kinetic_energy(vehicle, derived, v1))
        return s1, (s1, eqx.tree_at(lambda e: e.stores, ev, stores)), (ev.accel, ev.power)

    def step(self, model, vehicle, s, scene, derived, dt):
        """One step on its own (two evaluations: the carried one made first)."""
        ev0 = model.evaluate(vehicle, s, scene, derived)
        s1, _, _ = self.step_carried(model, vehicle, s, scene, derived, dt, self.start(ev0))
        return s1, ev0
