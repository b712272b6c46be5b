"""The stability limit of a method for a vehicle, as one call."""

from __future__ import annotations

from .._models import AbstractModel, QuarterModel
from .._params import Vehicle
from ._base import AbstractIntegrator
from ._names import integrator


def stable_step(vehicle: Vehicle, *, honeycomb_force=None, normal_force=None,
                bottomed: bool = False, method: str | AbstractIntegrator = "euler",
                impulse=None, model: AbstractModel = QuarterModel()):
    """Estimated stability limit of ``method`` [s] for ``vehicle``: the method's
    ``stable_step`` of the model's ``Oscillator`` (the foot held by the stiffest springs, damped
    by the strut and the ground). Without forces given, the a-priori limit assumes the second
    plateau F2 for both dampers; after a run, pass the peak honeycomb and normal forces it
    reached (and whether it bottomed out). ``impulse`` [N s]: the impulse step of "impulse"
    (default ``Impulse.dI``). "tsit5" has no fixed-step limit: inf."""
    options = {} if impulse is None else {"impulse": impulse}
    osc = model.oscillator(vehicle, honeycomb_force, normal_force, bottomed)
    return integrator(method, **options).stable_step(osc)
