"""Sampling: sample i's inputs depend only on (seed, i, input name)."""

from __future__ import annotations

import zlib

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import ConfigError
from .._scene import Scene
from ._spec import DISPERSIBLE, MonteCarloSpec


def sample_scenes(spec: MonteCarloSpec, start: int, count: int, n_legs: int = 4, *,
                  indices=None):
    """Scenes ``start .. start + count - 1`` of the spec (or the samples ``indices``), as a
    ``Scene.batch``, with the sampled inputs (TOML units; per-leg inputs as (count, n_legs))."""
    for key, val in spec.fixed.items():
        if DISPERSIBLE[key].component == "legs" and np.ndim(val) == 1 and len(val) != n_legs:
            raise ConfigError(f"fixed.{key}", val, f"must have one entry per leg ({n_legs})")
    names = sorted(spec.dispersion)
    root = jax.random.key(spec.seed)
    idx = jnp.arange(start, start + count) if indices is None else jnp.asarray(indices)
    count = int(idx.shape[0])

    def one(i):
        k = jax.random.fold_in(root, i)
        out = {}
        for name in names:
            shape = (n_legs,) if DISPERSIBLE[name].component == "legs" else ()
            key = jax.random.fold_in(k, zlib.crc32(name.encode()) & 0x7FFFFFFF)
            out[name] = spec.dispersion[name].sample(key, shape)
        return out

    inputs = {k: np.asarray(v) for k, v in jax.vmap(one)(idx).items()} if names else {}
    fields: dict = {}
    com = None
    for name, value in [*inputs.items(), *spec.fixed.items()]:
        target, to_si, comp = DISPERSIBLE[name]
        val = np.broadcast_to(np.asarray(value, dtype=float) * to_si,
                              (count, n_legs) if comp == "legs" else (count,))
        if target == "com_offset":
            com = np.zeros((count, 3)) if com is None else com
            com[:, comp] = val
        else:
            fields[target] = val
    if com is not None:
        fields["com_offset"] = com
    if not fields:
        fields["drop_height"] = np.full(count, 0.2)
    scenes = Scene.batch(**{k: jnp.asarray(v) for k, v in fields.items()})
    return scenes, inputs
