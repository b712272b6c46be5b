"""The paper's discrete-impulse method (sections 2.2, 2.4), for models with one primary force.

In a contact state the impulse of the normal ground spring is the independent variable (paper
Eqs 4-9): each step advances it by dI, so the step lasts dt = dI / F_zs, and every other impulse
(buffer, auxiliary strut, tangential, damping, gravity) is tied to it by its force ratio,
dI_j = (F_j / F_zs) dI = F_j dt. While only the buffer is loaded (state 4) the buffer impulse is
the primary one (paper 2.4); in the air (state 1) time steps, at solver.dt. The state update of
one step is then a symplectic Euler step of length dt, with the same laws and state machine as
the other methods.

Where the paper is ambiguous, and what we chose:
- Spring energy as a state. The paper advances the normal spring's energy E_zs with
  dE_zs/dI_zs = -v_z and takes F_zs = sqrt(2 k E_zs). We take the force from the penetration
  instead (the same in exact arithmetic): a separate energy state drifts away from the foot
  position (seen in a prototype) and cannot carry the pit memory.
- Step bounds. dt = dI / F is infinite at the first touch (F = 0; the integral t ~ sqrt(I) is
  finite) and long wherever the ground force is small, where the stiffer buffer, integrated
  explicitly, would blow up: dt is capped at solver.dt (a stable explicit step). A grazing
  re-contact with the foot's momentum below dI would loop with time frozen: dt is floored at
  MIN_STEP_FRACTION x the cap.
- Save points. A step is shortened to land on the next save time, so trajectories of every
  method share one time grid.
- The primary force is the total normal force (the spring force times the damping factor
  1 + chi d_dot, which differs from the spring force by < 1e-3 on the paper's gear).
- A stability guard the paper does not have: the step also satisfies dt <= dI / F_bh, the
  honeycomb force (``impulse_step_force``). Near a lift-off the ground force fades while the
  buffer still carries kilonewtons, and dt = dI / F_zs alone would let the strut damping
  D_b F_bh act over a step past its explicit limit. With the guard, c dt <= (D_b + chi) dI / m2
  holds whatever the forces, which is the limit ``Impulse.stable_step`` states.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._errors import ConfigError
from .._models import AbstractImpulseModel
from ._base import AbstractIntegrator, forward_only, positive
from ._loop import Track, advance, kick, record, setup, summary

# shortest time step, as a fraction of its cap solver.dt: a grazing contact with a tiny force
# would otherwise ask for dt = dI / F -> infinity (capped), and a force spike for dt -> 0 with
# time frozen (floored)
MIN_STEP_FRACTION = 1e-3
ADJOINTS = ("forward", "reverse")


def check_adjoint(owner: str, adjoint: str) -> None:
    if adjoint not in ADJOINTS:
        raise ConfigError(f"{owner}.adjoint", adjoint, "must be 'forward' or 'reverse'")


def _forward_only(x):
    return forward_only(x, "solver.adjoint", "forward", "has no reverse-mode derivative "
                        "(jax.grad, jax.vjp): its while loop differentiates forward only "
                        "(jax.jacfwd, jax.jvp); for jax.grad use "
                        "jaxland.Impulse(adjoint='reverse')")


class Impulse(AbstractIntegrator):
    """The discrete-impulse method (module docstring): ``dI`` [N s] is the impulse step,
    ``solver.dt`` caps the time step and is the step in the air. ``adjoint``: "forward"
    (jax.jacfwd / jvp) or "reverse" (jax.grad, a checkpointed while loop)."""

    dI: float = eqx.field(static=True, default=0.05)  # N s
    adjoint: str = eqx.field(static=True, default="forward")

    name: ClassVar[str] = "impulse"
    stability_reason: ClassVar[str] = (
        "its explicit steps are capped at dt: stiffest springs on the foot, and the strut "
        "damping over one impulse step")

    def validate(self):
        positive("solver", "impulse", self.dI, " N s")
        check_adjoint("solver", self.adjoint)
        return self

    def check_model(self, model):
        if not isinstance(model, AbstractImpulseModel):
            raise ConfigError(
                "solver.method", self.name,
                f"is available for the quarter model only ({model.name}: its feet each have "
                "their own normal impulse, so the paper's single primary impulse is undefined); "
                "use one of euler, euler_implicit, verlet, leapfrog")

    def stable_step(self, osc):
        """Steps dt = min(dI / F, cap) with explicit forces, and the damping grows with the same
        force F that shortens the step: c dt <= (D_b + chi) dI / m whatever F. The worst case
        of dt^2 omega^2 + 2 dt c <= 4 is at F = dI / cap, so the limit on the cap [s] is
        sqrt(4 - 2 dI (D_b + chi) / m) / omega, and there is none (0) once
        dI >= 2 m / (D_b + chi): a limit on the impulse step itself."""
        w2 = osc.stiffness / osc.mass
        room = 4.0 - 2.0 * self.dI * (osc.strut_damping + osc.ground_damping) / osc.mass
        return jnp.min(jnp.sqrt(jnp.maximum(room, 0.0) / w2))

    def integrate(self, model, vehicle, scene, solver):
        st = setup(model, vehicle, scene, solver)
        veh, derived = st.vehicle, st.derived
        cap, d_impulse = solver.dt, self.dI
        dt_floor = cap * MIN_STEP_FRACTION
        t_save = solver.dt * solver.save_every  # the save interval [s]

        def step_to(target):
            def body(carry):
                s, track = carry
                ev = model.evaluate(veh, s, scene, derived)
                f_p = model.impulse_step_force(ev.record)
                active = f_p > 0.0
                dt = jnp.where(active, d_impulse / jnp.where(active, f_p, 1.0), cap)
                dt = jnp.minimum(jnp.clip(dt, dt_floor, cap), target - s.t)
                v1 = kick(s.v, ev.accel, dt)
                s1 = advance(ev.state, s, model.drift(s.q, v1, dt), v1, dt, dt * ev.power)
                return s1, track.update(model, s, ev, st.energy0, st.energy_scale)
            return body

        kind = "lax" if self.adjoint == "forward" else "checkpointed"
        max_steps = int(math.ceil(t_save / dt_floor)) + 2

        def save_block(carry, i):
            out = (record(model, carry[0], model.evaluate(veh, carry[0], scene, derived),
                          st.energy0) if solver.trajectory else {})
            target = (i + 1.0) * t_save
            # the last step lands on the save time exactly (up to round-off in t)
            cond = lambda c: c[0].t < target - 1e-9 * t_save  # noqa: E731
            carry = eqx.internal.while_loop(cond, step_to(target), carry, max_steps=max_steps,
                                            kind=kind)
            return carry, out

        carry0 = (st.state0, Track.start(st.peaks0, solver.event_log))
        try:
            (s_end, track), traj = jax.lax.scan(save_block, carry0,
                                                jnp.arange(solver.n_saves, dtype=jnp.float64))
        except TypeError as err:  # JAX's own refusal says nothing of the adjoint option
            if kind != "checkpointed" or "forward-mode" not in str(err):
                raise
            raise ConfigError(
                "solver.adjoint", "reverse", "has no forward-mode derivative (jax.jacfwd, "
                "jax.jvp): its checkpointed while loop differentiates in reverse only "
                "(jax.grad, jax.vjp); for jax.jacfwd use jaxland.Impulse(adjoint='forward')"
            ) from None
        out = traj, summary(model, s_end, track, st, scene)
        return jax.tree.map(_forward_only, out) if kind == "lax" else out
