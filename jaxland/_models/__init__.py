"""Landing models: one contract (``AbstractModel``), the quarter model of a symmetric vertical
drop and the full 3-D vehicle."""

from ._base import (
    AbstractImpulseModel as AbstractImpulseModel,
    AbstractModel as AbstractModel,
    AbstractODEModel as AbstractODEModel,
    Evaluation as Evaluation,
    Oscillator as Oscillator,
    Smoothing as Smoothing,
)
from ._full import FullModel as FullModel
from ._quarter import QuarterModel as QuarterModel

MODELS = {"quarter": QuarterModel(), "full": FullModel()}
