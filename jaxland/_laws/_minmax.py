"""Maximum, minimum and clip for the laws' hot paths, one compare-and-select each.

``jnp.maximum`` lowers on XLA:CPU to LLVM's ``maximum``, which propagates a NaN in either
operand and orders -0 below +0; x86 has no instruction for that, so each one costs a max, an
unordered compare and a blend. ``fmax(x, y)`` is ``y if y > x else x``: one ``maxsd``. The
values agree with ``jnp.maximum`` except that a NaN propagates from ``x`` only (pass the
operand that carries the state first; a NaN state is caught by the landing's failure check in
any case) and that a tie of -0 and +0 returns ``x``. Derivatives are ``jnp.maximum``'s (a tie
splits the tangent in halves), so gradients do not change.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


@jax.custom_jvp
def fmax(x, y):
    """max(x, y); a NaN in ``x`` propagates."""
    return jnp.where(y > x, y, x)


@jax.custom_jvp
def fmin(x, y):
    """min(x, y); a NaN in ``x`` propagates."""
    return jnp.where(y < x, y, x)


@fmax.defjvp
def _fmax_jvp(primals, tangents):
    return fmax(*primals), jax.jvp(jnp.maximum, primals, tangents)[1]


@fmin.defjvp
def _fmin_jvp(primals, tangents):
    return fmin(*primals), jax.jvp(jnp.minimum, primals, tangents)[1]


def fclip(x, lo, hi):
    """min(max(x, lo), hi) with ``fmax`` and ``fmin``."""
    return fmin(fmax(x, lo), hi)
