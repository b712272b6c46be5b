"""Auxiliary strut of the inverted triangle: a massless linear spring (paper section 2.1)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp


class AuxOut(eqx.Module):
    force: jnp.ndarray  # N, compressive positive
    elastic_energy: jnp.ndarray  # J


def aux_strut(length, rest_length, k_a) -> AuxOut:
    """Axial force [N] (compression positive) of the auxiliary strut at ``length`` [m]."""
    e = rest_length - length
    return AuxOut(force=k_a * e, elastic_energy=0.5 * k_a * e**2)
