"""calibration: fit jaxland's quarter model to drop-test traces (force, stroke, acceleration),
with uncertainty, identifiability checks and a prediction check on other drops.

Uses jaxland's public API only. Typical use::

    import calibration as cal
    drops = cal.load_drop_tests(["data/synthetic/drop_h0.20m.toml"])
    result = cal.fit(drops)                    # k, gamma, D_b, k_b1, F1, F2 by default
    result.report()["parameters"]              # values, standard errors, identifiability
    cal.predict(result.vehicle, cal.load_drop_test("data/synthetic/drop_h0.30m.toml")).metrics

Command line (wired into ``jaxland``): ``jaxland fit DATA... --out DIR`` and
``jaxland predict --config FITTED.toml DATA``.
"""

from ._data import (
    CHANNELS as CHANNELS,
    DropTest as DropTest,
    load_drop_test as load_drop_test,
    load_drop_tests as load_drop_tests,
)
from ._fit import (
    INTEGRATOR as INTEGRATOR,
    INTEGRATORS as INTEGRATORS,
    REFINE_WINDOW_S as REFINE_WINDOW_S,
    SMOOTHING as SMOOTHING,
    WINDOWS_S as WINDOWS_S,
    FitResult as FitResult,
    IdentifiabilityWarning as IdentifiabilityWarning,
    MisfitWarning as MisfitWarning,
    fit as fit,
)
from ._parameters import (
    DEFAULT_PARAMS as DEFAULT_PARAMS,
    OPTIONAL_PARAMS as OPTIONAL_PARAMS,
    PARAMS as PARAMS,
)
from ._predict import Prediction as Prediction, predict as predict
from ._problem import CalibrationProblem as CalibrationProblem

__all__ = [
    "CHANNELS", "DropTest", "load_drop_test", "load_drop_tests", "fit", "FitResult",
    "IdentifiabilityWarning", "MisfitWarning", "WINDOWS_S", "REFINE_WINDOW_S", "INTEGRATOR",
    "INTEGRATORS",
    "SMOOTHING", "DEFAULT_PARAMS",
    "OPTIONAL_PARAMS", "PARAMS", "predict", "Prediction", "CalibrationProblem",
]
