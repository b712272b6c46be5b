"""jaxland: a differentiable JAX simulator of a vertical-landing vehicle on crushable
honeycomb landing gear. float64 is switched on at import; all quantities are SI."""

import os as _os

__version__ = "0.1.0"

# XLA:CPU compiles a while loop into one native kernel only when it is "small" by the bytes its
# buffers touch and holds no scatter and no library (YNNPACK/XNNPACK) fusion; otherwise every
# one of a step's fused kernels is dispatched separately on every iteration. A landing's step is
# exactly that kind of loop: its parameters count against the byte threshold whenever they are
# traced (fits, design, Monte Carlo), and a vmapped full 3-D step's small products and sums
# become YNNPACK fusions. With these options single landings and vmapped batches of both models
# compile their time loop into one kernel (docs/performance.md). They must be set before the XLA
# backend starts; an option the user sets in XLA_FLAGS is left alone.
_XLA_OPTIONS = {
    "xla_backend_extra_options": "xla_cpu_small_while_loop_byte_threshold=100000000",
    "xla_cpu_experimental_ynn_fusion_type": "",
    "xla_cpu_experimental_xnn_fusion_type": "",
    "xla_cpu_use_xnnpack": "false",
}
_flags = _os.environ.get("XLA_FLAGS", "")
_os.environ["XLA_FLAGS"] = " ".join(
    [_flags, *(f"--{k}={v}" for k, v in _XLA_OPTIONS.items() if k not in _flags)]).strip()

import jax as _jax  # noqa: E402


def _backend_started() -> bool:
    try:  # a private API: where it is missing, no warning
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return False


_BATCH_FUSION = "xla_cpu_use_multi_output_fusion"


def use_batch_fusion() -> bool:
    """Turn on XLA:CPU's multi-output fusion in this process, for batches of landings without a
    trajectory (Monte Carlo, design; ``jaxland montecarlo`` and ``jaxland design`` call it).
    Without it, every kernel that reads a value recomputes the elementwise work behind it; with
    it, one kernel computes the value for all of them. A vmapped step then costs less than half
    (quarter) or about 0.6x (3-D model), but a landing that saves a trajectory costs many times
    more and a fit about 8x (measured in docs/performance.md), so it is not on by default.
    Call it right after ``import jaxland``, before any JAX work: the option is read when XLA's
    backend starts.
    Returns whether it is on (False: the backend had started without it)."""
    flags = _os.environ.get("XLA_FLAGS", "")
    if _BATCH_FUSION in flags:
        return True
    if _backend_started():
        return False
    key = "--xla_backend_extra_options="
    words = flags.split()
    for i, word in enumerate(words):
        if word.startswith(key):
            words[i] = word + ("," if word != key else "") + _BATCH_FUSION
            break
    else:
        words.append(key + _BATCH_FUSION)
    _os.environ["XLA_FLAGS"] = " ".join(words)
    return True


if _backend_started():
    import warnings as _warnings

    _warnings.warn("jaxland was imported after JAX started its backend: its XLA:CPU options "
                   "(docs/performance.md) do not apply in this process, and landings run "
                   "slower; import jaxland before any JAX work", RuntimeWarning, stacklevel=2)

_jax.config.update("jax_enable_x64", True)

from . import _laws as laws
from ._config import (
    PAPER_CELLS as PAPER_CELLS,
    load_vehicle as load_vehicle,
    paper_vehicle as paper_vehicle,
    plateau_forces_from_cells as plateau_forces_from_cells,
    validate_vehicle as validate_vehicle,
    vehicle_from_dict as vehicle_from_dict,
    vehicle_to_toml as vehicle_to_toml,
)
from ._crush import plateau_force as plateau_force
from ._design import (
    DesignProblem as DesignProblem,
    DesignResult as DesignResult,
    DesignSpec as DesignSpec,
    apply_design as apply_design,
    design_spec_from_dict as design_spec_from_dict,
    design_verified as design_verified,
    gear_mass_kg as gear_mass_kg,
    load_design_spec as load_design_spec,
    optimise_design as optimise_design,
    risk_measure as risk_measure,
    verify_design as verify_design,
)
from ._errors import (
    ConfigError as ConfigError,
    JaxlandError as JaxlandError,
    SimulationError as SimulationError,
)
from ._files import (
    atomic_savefig as atomic_savefig,
    atomic_write_csv as atomic_write_csv,
    atomic_write_text as atomic_write_text,
    check_out as check_output_folder,
    staged as staged,
)
from ._models import (
    AbstractModel as AbstractModel,
    Evaluation as Evaluation,
    FullModel as FullModel,
    Oscillator as Oscillator,
    QuarterModel as QuarterModel,
)
from ._montecarlo import (
    Distribution as Distribution,
    MonteCarloResult as MonteCarloResult,
    MonteCarloSpec as MonteCarloSpec,
    init_distributed as init_distributed,
    load_montecarlo_spec as load_montecarlo_spec,
    run_montecarlo as run_montecarlo,
    sample_scenes as sample_scenes,
    wilson_interval as wilson_interval,
)
from ._params import Ground as Ground, Honeycomb as Honeycomb, Leg as Leg, Vehicle as Vehicle
from ._plots import (
    plot_design as plot_design,
    plot_landing as plot_landing,
    plot_landing_3d as plot_landing_3d,
    plot_montecarlo as plot_montecarlo,
)
from ._progress import ProgressLine as ProgressLine
from ._scene import (
    Scene as Scene,
    batch_axes as batch_axes,
    load_scene as load_scene,
    scene_from_dict as scene_from_dict,
    scene_to_toml as scene_to_toml,
)
from ._simulate import (
    Landing as Landing,
    choose_model as choose_model,
    landing as landing,
    landings as landings,
    simulate as simulate,
)
from ._solvers import (
    CLOSURE_LIMIT as CLOSURE_LIMIT,
    FIXED_STEP_METHODS as FIXED_STEP_METHODS,
    METHODS as METHODS,
    AbstractIntegrator as AbstractIntegrator,
    Euler as Euler,
    EulerImplicit as EulerImplicit,
    Impulse as Impulse,
    Leapfrog as Leapfrog,
    Result as Result,
    Solver as Solver,
    Tsit5 as Tsit5,
    Verlet as Verlet,
    integrator as integrator,
    stable_step as stable_step,
)
from ._toml import read_text as read_text

__all__ = [
    "laws", "load_vehicle", "paper_vehicle", "validate_vehicle", "vehicle_from_dict",
    "vehicle_to_toml", "plateau_force", "ConfigError", "JaxlandError", "SimulationError", "Solver",
    "stable_step", "Ground", "Honeycomb", "Leg", "Vehicle", "Scene", "load_scene",
    "scene_from_dict", "Landing", "choose_model", "landing", "landings", "simulate", "batch_axes",
    "DesignProblem", "DesignResult", "DesignSpec", "design_spec_from_dict", "load_design_spec",
    "optimise_design", "verify_design", "design_verified", "METHODS", "FIXED_STEP_METHODS",
    "Distribution",
    "MonteCarloResult", "MonteCarloSpec", "load_montecarlo_spec", "run_montecarlo",
    "sample_scenes", "wilson_interval", "plot_landing", "plot_landing_3d", "plot_design",
    "plot_montecarlo", "atomic_savefig", "atomic_write_text", "staged", "AbstractModel",
    "Evaluation", "FullModel", "Oscillator", "QuarterModel", "AbstractIntegrator", "Euler",
    "EulerImplicit", "Impulse", "Leapfrog", "Result", "Tsit5", "Verlet", "integrator",
    "ProgressLine",
    "scene_to_toml", "init_distributed", "atomic_write_csv", "check_output_folder", "read_text",
    "PAPER_CELLS", "CLOSURE_LIMIT", "use_batch_fusion", "plateau_forces_from_cells", "apply_design",
    "gear_mass_kg", "risk_measure",
]
