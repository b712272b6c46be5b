"""Integrators: one contract (``AbstractIntegrator``), five methods, every model that has what
each method needs. ``Solver`` holds the settings they share."""

from ._base import (
    AbstractIntegrator as AbstractIntegrator,
    Result as Result,
    Solver as Solver,
)
from ._fixed import (
    AbstractFixedStep as AbstractFixedStep,
    Euler as Euler,
    EulerImplicit as EulerImplicit,
    Verlet as Verlet,
)
from ._impulse import Impulse as Impulse
from ._loop import ENERGY_TOLERANCE as ENERGY_TOLERANCE, N_EVENTS as N_EVENTS
from ._names import (
    FIXED_STEP_METHODS as FIXED_STEP_METHODS,
    INTEGRATORS as INTEGRATORS,
    METHODS as METHODS,
    integrator as integrator,
)
from ._stability import stable_step as stable_step
from ._tsit5 import Tsit5 as Tsit5
from ._verdict import (
    CLOSURE_LIMIT as CLOSURE_LIMIT,
    step_limit_reached as step_limit_reached,
    verdict as verdict,
)


def integrate(model, vehicle, scene, solver: Solver):
    """One landing of ``model`` with ``solver``: ``(trajectory, summary)``. Pure, jittable."""
    solver.method.check_model(model)
    return solver.method.integrate(model, vehicle, scene, solver)
