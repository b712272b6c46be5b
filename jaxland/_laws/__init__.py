"""Constitutive laws, one element each, written for one leg / one foot.

Every law is a pure function of the current kinematics, the element's memory and its parameters,
returns the updated memory with the force, and is safe under jit, vmap, grad and jacfwd: every
branch of every ``where`` is finite for every input, so no NaN gradient appears at zero stroke,
zero penetration or any breakpoint. Batch them with ``jax.vmap``.
"""

from ._aux import AuxOut as AuxOut, aux_strut as aux_strut
from ._contact import (
    NormalOut as NormalOut,
    TangentialOut as TangentialOut,
    normal_contact as normal_contact,
    safe_hypot as safe_hypot,
    safe_sqrt as safe_sqrt,
    tangential_contact as tangential_contact,
)
from ._honeycomb import (
    HoneycombOut as HoneycombOut,
    honeycomb as honeycomb,
    honeycomb_virgin_force as honeycomb_virgin_force,
    primary_peak_excess as primary_peak_excess,
)
from ._strut import (
    StrutOut as StrutOut,
    strut_force as strut_force,
)
