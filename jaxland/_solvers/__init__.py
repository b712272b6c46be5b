"""Integrators: one contract (``AbstractIntegrator``), six methods, every model that has what
each method needs. ``Solver`` holds the settings they share."""

import jax
import jax.numpy as jnp

from .._config import follows_rules
from ._base import (
    ENERGY_TOLERANCE as ENERGY_TOLERANCE,
    FAILED_CODES as FAILED_CODES,
    N_EVENTS as N_EVENTS,
    AbstractIntegrator as AbstractIntegrator,
    Result as Result,
    Solver as Solver,
    check_spec_steps as check_spec_steps,
)
from ._fixed import (
    AbstractFixedStep as AbstractFixedStep,
    Euler as Euler,
    EulerImplicit as EulerImplicit,
    Leapfrog as Leapfrog,
    Verlet as Verlet,
)
from ._impulse import Impulse as Impulse
from ._names import (
    FIXED_STEP_METHODS as FIXED_STEP_METHODS,
    INTEGRATORS as INTEGRATORS,
    METHODS as METHODS,
    integrator as integrator,
)
from ._stability import scene_force_bound as scene_force_bound, stable_step as stable_step
from ._tsit5 import Tsit5 as Tsit5
from ._verdict import (
    CLOSURE_LIMIT as CLOSURE_LIMIT,
    step_limit_reached as step_limit_reached,
    verdict as verdict,
)


def integrate(model, vehicle, scene, solver: Solver):
    """One landing of ``model`` with ``solver``: ``(trajectory, summary)``. Pure, jittable.

    The summary's ``result`` is the landing's ``verdict`` (a ``Result`` code;
    ``OUTSIDE_ENVELOPE`` for a scene outside ``Scene.inside_envelope``, or not
    ``Scene.symmetric`` for the quarter model; ``INVALID_VEHICLE`` for a vehicle with a field
    outside its own rule, ``jaxland._config.follows_rules``, traced ones included), and
    ``bottomed`` says whether the stroke reached the bottoming stop (where the stroke's
    derivatives are the stop's, not the honeycomb's). Every output of a failed landing keeps
    its value (for the diagnosis) but has NaN derivatives: a failure never passes as a
    gradient. The solver's settings are checked first (``Solver.validate``; a
    ``ConfigError`` names the one refused)."""
    solver.validate()
    solver.method.check_model(model)
    traj, summary = solver.method.integrate(model, vehicle, scene, solver)
    inside = scene.inside_envelope()
    if model.name == "quarter":  # it represents symmetric vertical drops only
        inside = inside & scene.symmetric()
    code = jnp.where(inside, verdict(summary, vehicle, solver, model),
                     int(Result.OUTSIDE_ENVELOPE))
    # a traced vehicle (a user's optimiser stepping out of a field's rule) escapes
    # validate_vehicle: its landing is no valid one, and its derivatives are NaN
    code = jnp.where(follows_rules(vehicle), code,
                     int(Result.INVALID_VEHICLE)).astype(jnp.int32)
    failed = jnp.isin(code, jnp.asarray(FAILED_CODES, code.dtype))
    summary = dict(summary, result=code, bottomed=model.leg_max(summary["max_stroke_m"])
                   > jnp.min(vehicle.honeycomb.x_L4))
    return _nan_derivatives((traj, summary), failed)


@jax.custom_jvp
def _guard(x, bad):
    return x


@_guard.defjvp
def _guard_jvp(primals, tangents):
    x, bad = primals
    return x, tangents[0] * jnp.where(bad, jnp.nan, 1.0)


def _nan_derivatives(tree, bad):
    """``tree`` unchanged, its floating leaves' derivatives NaN where ``bad``."""
    return jax.tree.map(
        lambda x: _guard(x, bad) if jnp.issubdtype(jnp.result_type(x), jnp.floating) else x,
        tree)
