"""Integrators by name (the CLI's, the TOML specs' and ``Solver(method="...")``'s vocabulary)."""

from __future__ import annotations

from .._errors import ConfigError
from ._base import AbstractIntegrator
from ._fixed import AbstractFixedStep, Euler, EulerImplicit, Leapfrog, Verlet
from ._impulse import Impulse
from ._tsit5 import Tsit5

INTEGRATORS: dict[str, type[AbstractIntegrator]] = {
    cls.name: cls for cls in (Euler, EulerImplicit, Verlet, Leapfrog, Impulse, Tsit5)}
METHODS = tuple(INTEGRATORS)
# the methods with one step size throughout (early stopping, a sparse ledger, Monte Carlo)
FIXED_STEP_METHODS = tuple(n for n, c in INTEGRATORS.items() if issubclass(c, AbstractFixedStep))
# option names as the CLI and simulate() spell them -> the integrator's field
_OPTION_FIELDS = {"impulse": "dI", "rtol": "rtol", "atol": "atol", "max_steps": "max_steps",
                  "adjoint": "adjoint"}


def integrator(method: str | AbstractIntegrator, **options) -> AbstractIntegrator:
    """The integrator named ``method`` with ``options`` (``impulse`` [N s] for "impulse";
    ``rtol``, ``atol``, ``max_steps`` for "tsit5"; ``adjoint`` for both), validated.

    Raises ``ConfigError`` for an unknown method, or an option the method does not take."""
    if isinstance(method, AbstractIntegrator):
        if options:
            raise ConfigError(f"solver.{next(iter(options))}", options[next(iter(options))],
                              "is given twice: set it on the integrator object")
        return method.validate()
    if method not in INTEGRATORS:
        raise ConfigError("solver.method", method, f"must be one of {', '.join(METHODS)}")
    cls = INTEGRATORS[method]
    kwargs = {}
    for name, val in options.items():
        field = _OPTION_FIELDS.get(name, name)
        if field not in cls.__dataclass_fields__:
            takes = [k for k, f in _OPTION_FIELDS.items() if f in cls.__dataclass_fields__]
            raise ConfigError(f"solver.{name}", val,
                              f"is not an option of {method} (it takes "
                              f"{', '.join(takes) if takes else 'none'})")
        kwargs[field] = val
    return cls(**kwargs).validate()
