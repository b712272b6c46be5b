"""jaxland: a differentiable JAX simulator of a vertical-landing vehicle on crushable
honeycomb landing gear. float64 is switched on at import; all quantities are SI."""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from . import _laws as laws  # noqa: E402
from ._config import (  # noqa: E402
    load_vehicle as load_vehicle,
)
from ._config import (
    paper_vehicle as paper_vehicle,
)
from ._config import (
    validate_vehicle as validate_vehicle,
)
from ._config import (
    vehicle_from_dict as vehicle_from_dict,
)
from ._config import (
    vehicle_to_toml as vehicle_to_toml,
)
from ._crush import plateau_force as plateau_force  # noqa: E402
from ._errors import (  # noqa: E402
    ConfigError as ConfigError,
)
from ._errors import (
    JaxlandError as JaxlandError,
)
from ._errors import (
    SimulationError as SimulationError,
)
from ._integrate import Solver as Solver  # noqa: E402
from ._integrate import stable_step as stable_step
from ._params import Ground as Ground  # noqa: E402
from ._params import Honeycomb as Honeycomb
from ._params import Leg as Leg
from ._params import Vehicle as Vehicle  # noqa: E402
from ._scene import Scene as Scene  # noqa: E402
from ._simulate import Landing as Landing  # noqa: E402
from ._simulate import landing as landing
from ._simulate import simulate as simulate

__all__ = [
    "laws", "load_vehicle", "paper_vehicle", "validate_vehicle", "vehicle_from_dict",
    "vehicle_to_toml", "plateau_force", "ConfigError", "JaxlandError", "SimulationError",
    "Solver", "stable_step", "Ground", "Honeycomb", "Leg", "Vehicle", "Scene", "Landing",
    "landing", "simulate",
]
__version__ = "0.1.0"
