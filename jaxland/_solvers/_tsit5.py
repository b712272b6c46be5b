"""Adaptive Runge-Kutta: diffrax's Tsit5 on the model's ODE form."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._errors import ConfigError
from .._models import AbstractODEModel
from ._base import AbstractIntegrator, Result, positive
from ._impulse import check_adjoint
from ._loop import Track, record, setup, summary


class Tsit5(AbstractIntegrator):
    """diffrax's Tsit5 with a PIDController (integral gain only, the classic controller) on the
    model's ODE form (memories in rate form). ``max_steps`` bounds the work, and reaching it (a
    stall at a discontinuity) is reported as a failure, as is any other solver failure.

    Its derivatives are not those of the landing: forward sensitivities of an adaptive method
    miss the jumps of a discontinuous right-hand side (contact, stick/slip, crush onset), with
    errors of order one (``benchmarks/gradient_quality.py``). Differentiating through it raises
    ``ConfigError``; use a fixed-step method for gradients.
    """

    rtol: float = eqx.field(static=True, default=1e-6)  # relative tolerance
    atol: float = eqx.field(static=True, default=1e-9)  # absolute tolerance, state units
    max_steps: int = eqx.field(static=True, default=1_000_000)
    adjoint: str = eqx.field(static=True, default="forward")

    name: ClassVar[str] = "tsit5"
    stability_reason: ClassVar[str] = "adaptive: no fixed-step limit"

    @property
    def differentiable(self) -> bool:
        return False

    def validate(self):
        positive("solver", "rtol", self.rtol, "")
        positive("solver", "atol", self.atol, "")
        if (isinstance(self.max_steps, bool) or not isinstance(self.max_steps, int)
                or self.max_steps < 1):
            raise ConfigError("solver.max_steps", self.max_steps, "must be an integer >= 1")
        check_adjoint("solver", self.adjoint)
        return self

    def check_model(self, model):
        if not isinstance(model, AbstractODEModel):
            raise ConfigError(
                "solver.method", self.name,
                f"is available for the quarter model only ({model.name}: its per-foot "
                "memories have no ODE form yet); use one of euler, euler_implicit, verlet")

    def stable_step(self, osc):
        return jnp.asarray(jnp.inf)

    def integrate(self, model, vehicle, scene, solver):
        """The first touchdown, found in closed form from the free fall, is a jump time of the
        controller so no step straddles it; later contact changes are found by step rejection.
        Peaks, the event log and the ledger are read at the save points."""
        import diffrax

        vehicle, scene = _no_derivatives((vehicle, scene))
        st = setup(model, vehicle, scene, solver)
        veh, derived = st.vehicle, st.derived
        ts = jnp.arange(solver.n_saves, dtype=jnp.float64) * solver.save_dt
        t1 = solver.n_saves * solver.save_dt
        g, v0, h = veh.g, scene.sink_speed, scene.drop_height
        t_touch = (jnp.sqrt(v0 * v0 + 2.0 * g * h) - v0) / g
        term = diffrax.ODETerm(lambda t, y, args: model.ode_rates(veh, t, y, scene, derived))
        controller = diffrax.ClipStepSizeController(
            diffrax.PIDController(rtol=self.rtol, atol=self.atol, pcoeff=0.0, icoeff=1.0,
                                  dtmax=solver.save_dt),
            jump_ts=jnp.reshape(t_touch, (1,)))
        adjoint = (diffrax.ForwardMode() if self.adjoint == "forward"
                   else diffrax.RecursiveCheckpointAdjoint())
        sol = diffrax.diffeqsolve(
            term, diffrax.Tsit5(), 0.0, t1, solver.dt, model.ode_state(st.state0),
            saveat=diffrax.SaveAt(ts=jnp.append(ts, t1)), stepsize_controller=controller,
            max_steps=self.max_steps, throw=False, adjoint=adjoint)
        ok = sol.result == diffrax.RESULTS.successful
        states = jax.vmap(model.from_ode)(sol.ts, sol.ys)

        def look(track, s):  # one evaluation per saved state, for the bookkeeping and record
            ev = model.evaluate(veh, s, scene, derived)
            return (track.update(model, s, ev, st.energy0, st.energy_scale),
                    record(model, s, ev, st.energy0))

        track, traj = jax.lax.scan(look, Track.start(st.peaks0, solver.event_log), states)
        traj = jax.tree.map(lambda x: x[:-1], traj)  # the last state, at t1, is not saved
        s_end = jax.tree.map(lambda x: x[-1], states)
        out = summary(model, s_end, track, st, scene)
        # a solver that stopped early leaves the save points it never reached at inf
        reached = jnp.isfinite(sol.ts)
        t_stop = jnp.max(jnp.where(reached, sol.ts, 0.0))
        fail_t = jnp.where(ok, out["failure_time_s"],
                           jnp.where((out["failure_time_s"] >= 0.0)
                                     & (out["failure_time_s"] <= t_stop),
                                     out["failure_time_s"], t_stop))
        out.update(failed=fail_t >= 0.0, failure_time_s=fail_t, solver_ok=ok,
                   t_end_s=jnp.where(ok, out["t_end_s"], t_stop),
                   n_steps=sol.stats["num_accepted_steps"].astype(jnp.int32),
                   n_rejected_steps=sol.stats["num_rejected_steps"].astype(jnp.int32),
                   result=jnp.where(ok, out["result"],
                                    int(Result.SOLVER_STOPPED)).astype(jnp.int32))
        return traj, out


@jax.custom_jvp
def _no_derivatives(x):
    """Identity whose derivative is refused: Tsit5's sensitivities are wrong (class doc)."""
    return x


@_no_derivatives.defjvp
def _no_derivatives_jvp(primals, tangents):
    raise ConfigError("solver.method", "tsit5", "cannot be differentiated: its sensitivities "
                      "miss the jumps of the contact switches (errors of order one); use "
                      "euler, euler_implicit or verlet for gradients")
