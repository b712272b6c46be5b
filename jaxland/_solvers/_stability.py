"""The stability limit of a method for a vehicle, as one call."""

from __future__ import annotations

import functools
import math

import jax
import numpy as np

from .._models import AbstractModel, QuarterModel
from .._params import Vehicle
from ._base import AbstractIntegrator
from ._names import integrator


# compiled as one program: called eagerly (the front doors check a step before running), its
# dozen small operations would each be compiled on their own
@functools.partial(jax.jit, static_argnames=("method", "impulse", "model"))
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


def scene_force_bound(vehicle: Vehicle, scene, model: AbstractModel = QuarterModel()):
    """An upper bound of the honeycomb force a landing in ``scene`` can reach [N], and whether it
    bottoms out, from energy alone: the touchdown kinetic energy (vertical and horizontal) plus
    the fall through the stroke, of the body mass a leg carries (``model.leg_mass``), less the
    crush work the leg can absorb (F1 x_L2 + F2 (x_L4 - x_L2), an over-estimate); what is left
    compresses the bottoming stop, F <= F2 + sqrt(2 E k_bottom). Concrete scene values."""
    hc, g = vehicle.honeycomb, float(vehicle.g)
    v2 = float(scene.touchdown_speed(g)) ** 2 + float(scene.horizontal_speed) ** 2
    energy = float(model.leg_mass(vehicle)) * (0.5 * v2 + g * float(np.max(hc.x_L4)))
    capacity = float(np.min(hc.F1 * hc.x_L2 + hc.F2 * (hc.x_L4 - hc.x_L2)))
    excess = energy - capacity
    if excess <= 0.0:
        return float(np.max(hc.F2)), False
    return float(np.max(hc.F2)) + math.sqrt(2.0 * excess * float(hc.k_bottom)), True
