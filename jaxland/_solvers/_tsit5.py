"""Adaptive Runge-Kutta: diffrax's Tsit5 on the model's ODE form."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import Number
from .._errors import ConfigError
from .._models import AbstractODEModel
from ._base import MAX_STEPS, AbstractIntegrator, Result, positive
from ._impulse import check_adjoint
from ._loop import Track, record, setup, summary

# the tightest relative tolerance a float64 step can meet: a few times its rounding (2.2e-16)
RTOL_MIN = 1e-14


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
    dt_is_first_step: ClassVar[bool] = True

    @property
    def differentiable(self) -> bool:
        return False

    def validate(self):
        positive("solver", "rtol", self.rtol, "")
        positive("solver", "atol", self.atol, "")
        if self.rtol < RTOL_MIN:  # no float64 step meets it: the run would stall at max_steps
            raise ConfigError("solver.rtol", self.rtol, f"must be >= {RTOL_MIN:g}: below a "
                              "few float64 roundings no step can meet it")
        if isinstance(self.max_steps, bool) or not isinstance(self.max_steps, int):
            raise ConfigError("solver.max_steps", self.max_steps, "must be an integer >= 1")
        # no run takes more steps than MAX_STEPS, whatever its method; a budget far beyond it
        # overflows the integer the solver counts its steps in
        Number(integer=True, lo=1, hi=MAX_STEPS)("solver.max_steps", self.max_steps)
        check_adjoint("solver", self.adjoint)
        return self

    def check_model(self, model):
        if not isinstance(model, AbstractODEModel):
            raise ConfigError(
                "solver.method", self.name,
                f"is available for the quarter model only ({model.name}: its per-foot "
                "memories have no ODE form yet); use one of euler, euler_implicit, verlet, "
                "leapfrog")

    def stable_step(self, osc):
        return jnp.asarray(jnp.inf)

    def integrate(self, model, vehicle, scene, solver):
        """The first touchdown, found in closed form from the free fall, is a jump time of the
        controller so no step straddles it; later contact changes are found by step rejection.
        Peaks, the event log and the ledger are taken at every accepted step
        (``_tracked_class``), as the fixed-step methods take them at every step; the save
        points only sample the trajectory. The step is capped at the foot's time scale
        (``step_cap``), whatever the output interval, so that no step passes over a contact."""
        import diffrax

        vehicle, scene = _no_derivatives((vehicle, scene))
        st = setup(model, vehicle, scene, solver)
        veh, derived = st.vehicle, st.derived
        ts = jnp.arange(solver.n_saves, dtype=jnp.float64) * solver.save_dt
        t1 = solver.n_saves * solver.save_dt
        t_touch = scene.fall_time(veh.g)
        term = diffrax.ODETerm(lambda t, y, args: model.ode_rates(veh, t, y, scene, derived))
        controller = diffrax.ClipStepSizeController(
            diffrax.PIDController(rtol=self.rtol, atol=self.atol, pcoeff=0.0, icoeff=1.0,
                                  dtmax=step_cap(model, veh)),
            jump_ts=jnp.reshape(t_touch, (1,)))
        forward = self.adjoint == "forward"
        adjoint = diffrax.ForwardMode() if forward else diffrax.RecursiveCheckpointAdjoint()

        def update(t, y, track):  # the bookkeeping of one accepted step's end state
            s = model.from_ode(t, y)
            return track.update(model, s, model.evaluate(veh, s, scene, derived), st.energy0,
                                st.energy_scale)

        tracked = _tracked_class()(diffrax.Tsit5(scan_kind="lax" if forward else None), update,
                                   Track.start(st.peaks0, solver.event_log))
        sol = diffrax.diffeqsolve(
            term, tracked, 0.0, t1, solver.dt, model.ode_state(st.state0),
            saveat=diffrax.SaveAt(ts=jnp.append(ts, t1), solver_state=True),
            stepsize_controller=controller, max_steps=self.max_steps, throw=False,
            adjoint=adjoint)
        ok = sol.result == diffrax.RESULTS.successful
        track = sol.solver_state[1]
        states = jax.vmap(model.from_ode)(sol.ts[:-1], jax.tree.map(lambda x: x[:-1], sol.ys))
        traj = jax.vmap(lambda s: record(model, s, model.evaluate(veh, s, scene, derived),
                                         st.energy0))(states) if solver.trajectory else {}
        s_end = model.from_ode(sol.ts[-1], jax.tree.map(lambda x: x[-1], sol.ys))
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


def step_cap(model, vehicle):
    """The largest step [s]: 1 / omega of the model's stiffest, lightest oscillator (the foot
    on its stiffest springs, ``AbstractModel.oscillator``). A contact of that foot lasts about
    half a period, pi / omega (longer on the ground spring alone); Tsit5's stages lie at most
    0.57 of a step apart, so a step of 1 / omega puts a stage inside such a contact and the
    error estimate sees it."""
    osc = model.oscillator(vehicle)
    return jnp.min(jnp.sqrt(osc.mass / osc.stiffness))


@functools.cache
def _tracked_class():
    """``_Tracked``, built on first use: diffrax is imported only when tsit5 runs."""
    import diffrax

    class _Tracked(diffrax.AbstractWrappedSolver):
        """A diffrax solver that carries the landing's ``Track`` in its solver state and
        updates it with the end state of every step. diffrax keeps a step's new solver state
        only when the controller accepts the step, so the track sees exactly the accepted
        steps, at whatever interval the output is saved."""

        solver: diffrax.AbstractSolver
        update: Callable  # (t, y, track) -> track
        track0: Track

        @property
        def scan_kind(self):
            # diffrax's ForwardMode reads it (the wrapper passes for a Runge-Kutta method) and
            # needs "lax": it is set on the wrapped solver, as ForwardMode cannot set it here
            return self.solver.scan_kind

        @property
        def term_structure(self):
            return self.solver.term_structure

        @property
        def interpolation_cls(self):
            return self.solver.interpolation_cls

        @property
        def term_compatible_contr_kwargs(self):
            return self.solver.term_compatible_contr_kwargs

        def order(self, terms):
            return self.solver.order(terms)

        def strong_order(self, terms):
            return self.solver.strong_order(terms)

        def error_order(self, terms):
            return self.solver.error_order(terms)

        def init(self, terms, t0, t1, y0, args):
            return (self.solver.init(terms, t0, t1, y0, args),
                    self.update(t0, y0, self.track0))

        def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
            inner, track = solver_state
            y1, y_error, dense_info, inner, result = self.solver.step(
                terms, t0, t1, y0, args, inner, made_jump)
            return y1, y_error, dense_info, (inner, self.update(t1, y1, track)), result

        def func(self, terms, t0, y0, args):
            return self.solver.func(terms, t0, y0, args)

    return _Tracked


@jax.custom_jvp
def _no_derivatives(x):
    """Identity whose derivative is refused: Tsit5's sensitivities are wrong (class doc)."""
    return x


@_no_derivatives.defjvp
def _no_derivatives_jvp(primals, tangents):
    raise ConfigError("solver.method", "tsit5", "cannot be differentiated: its sensitivities "
                      "miss the jumps of the contact switches (errors of order one); use "
                      "euler, euler_implicit, verlet or leapfrog for gradients")
