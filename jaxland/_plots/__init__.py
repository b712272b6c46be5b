"""Figures of a landing (quarter and full 3-D), a Monte Carlo and a design. matplotlib is
imported only inside the plotting functions, so ``import jaxland`` does not load it."""

from ._design import plot_design as plot_design
from ._landing import REQUIRED_COLUMNS as REQUIRED_COLUMNS, plot_landing as plot_landing
from ._landing3d import (
    PER_LEG_COLUMNS as PER_LEG_COLUMNS,
    REQUIRED_COLUMNS_3D as REQUIRED_COLUMNS_3D,
    plot_landing_3d as plot_landing_3d,
)
from ._montecarlo import plot_montecarlo as plot_montecarlo
