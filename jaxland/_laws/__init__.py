"""Constitutive laws, one element each, written for one leg / one foot.

Every law is a pure function of the current kinematics, the element's memory and its parameters,
returns the updated memory with the force, and is safe under jit, vmap, grad and jacfwd: every
branch of every ``where`` is finite for every input, so no NaN gradient appears at zero stroke,
zero penetration or any breakpoint. Batch them with ``jax.vmap``.
"""

from ._aux import AuxOut as AuxOut
from ._aux import aux_strut as aux_strut
from ._contact import (
    NormalOut as NormalOut,
)
from ._contact import (
    TangentialOut as TangentialOut,
)
from ._contact import (
    normal_contact as normal_contact,
)
from ._contact import (
    safe_norm as safe_norm,
)
from ._contact import (
    tangential_contact as tangential_contact,
)
from ._honeycomb import (
    HoneycombOut as HoneycombOut,
)
from ._honeycomb import (
    honeycomb as honeycomb,
)
from ._honeycomb import (
    honeycomb_virgin_force as honeycomb_virgin_force,
)
from ._strut import (
    StrutOut as StrutOut,
)
from ._strut import (
    strut_force as strut_force,
)
