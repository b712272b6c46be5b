"""Is a landing's answer to be used? One rule for simulate, Monte Carlo and design."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._models import AbstractModel
from ._base import CLOSURE_LIMIT, Result, Solver
from ._stability import stable_step
from ._tsit5 import Tsit5


def verdict(summary: dict, vehicle, solver: Solver, model: AbstractModel):
    """The ``Result`` code of each landing in ``summary`` (one landing or a batch; jnp, so it
    runs inside jit as well as on the host).

    In order of precedence: a failure during the run (non-finite state, ledger blow-up, an
    adaptive solver that stopped); a ledger that does not close to ``CLOSURE_LIMIT`` of the
    energy dissipated; a fixed step above the stability limit of the forces the landing
    reached (its peak honeycomb and ground forces, and the bottoming stop's stiffness if it
    bottomed out); else the run's own code (successful, or no touchdown). After a tip-over the
    integrator stops checking, so this judges the landing up to the tip."""
    run = jnp.asarray(summary["result"])
    closure_bad = ~(summary["ledger_error_rel"] <= CLOSURE_LIMIT)
    code = jnp.where(closure_bad, int(Result.CLOSURE), run)
    if not isinstance(solver.method, Tsit5):
        limit = step_limit_reached(summary, vehicle, solver, model)
        code = jnp.where(~closure_bad & (solver.dt > limit), int(Result.STEP_ABOVE_LIMIT), code)
    failed_in_run = summary["failed"] | ~summary["solver_ok"]
    return jnp.where(failed_in_run, run, code).astype(jnp.int32)


def step_limit_reached(summary: dict, vehicle, solver: Solver, model: AbstractModel):
    """The method's stability limit [s] at the forces this landing reached."""
    h = model.leg_max(jnp.asarray(summary["peak_honeycomb_force_N"]))
    nf = model.leg_max(jnp.asarray(summary["peak_normal_force_N"]))
    bottomed = model.leg_max(jnp.asarray(summary["max_stroke_m"])) > jnp.min(
        vehicle.honeycomb.x_L4)

    def limit(h, nf, bottomed):
        return stable_step(vehicle, honeycomb_force=h, normal_force=nf, bottomed=bottomed,
                           method=solver.method, model=model)

    for _ in range(jnp.ndim(h)):  # batch axes
        limit = jax.vmap(limit)
    return limit(h, nf, bottomed)
