"""Sampling: sample i's inputs depend only on (seed, i, input name)."""

from __future__ import annotations

import functools
import numbers
import zlib

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import ConfigError
from .._scene import Scene
from ._spec import DISPERSIBLE, MonteCarloSpec, sample_kind


def sample_scenes(spec: MonteCarloSpec, start: int, count: int, n_legs: int = 4, *,
                  indices=None):
    """Scenes ``start .. start + count - 1`` of the spec (or the samples ``indices``), as a
    ``Scene.batch``, with the sampled inputs (TOML units; per-leg inputs as (count, n_legs))."""
    check_fixed(spec, n_legs)
    if indices is None:  # sample i is (seed, i): a negative or fractional i is no sample
        for name, v, least in (("start", start, 0), ("count", count, 1)):
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < least:
                raise ConfigError(name, v, f"must be an integer >= {least}")
    idx = jnp.arange(start, start + count) if indices is None else jnp.asarray(indices)
    count = int(idx.shape[0])
    inputs = {k: np.asarray(v) for k, v in draw(spec, idx, n_legs).items()}
    return Scene.batch(**scene_fields(spec, inputs, count, n_legs)), inputs


def check_fixed(spec: MonteCarloSpec, n_legs: int) -> None:
    """Refuse a fixed per-leg input with the wrong number of legs."""
    for key, val in spec.fixed.items():
        if DISPERSIBLE[key].component == "legs" and np.ndim(val) == 1 and len(val) != n_legs:
            raise ConfigError(f"fixed.{key}", val, f"must have one entry per leg ({n_legs})")


def draw(spec: MonteCarloSpec, idx, n_legs: int = 4) -> dict:
    """The dispersed inputs of the samples ``idx`` (TOML units, device arrays; no wait for the
    device): one compiled program for any chunk, so a sample's bits do not depend on the
    chunk that drew it."""
    dists = tuple(sorted(spec.dispersion.items()))
    return _draw(dists, spec.seed, idx, n_legs) if dists else {}


@functools.partial(jax.jit, static_argnums=(0, 3))
def _draw(dists: tuple, seed, idx, n_legs: int) -> dict:
    # the inputs of one kind and shape are drawn together (one vmapped draw each): the same
    # bits as one draw per input, in a program that compiles in about 0.6 of the time
    groups: dict = {}
    for name, dist in dists:
        legs = DISPERSIBLE[name].component == "legs"
        groups.setdefault((dist.kind, legs), []).append((name, dist))
    root = jax.random.key(seed)

    def one(i):
        k = jax.random.fold_in(root, i)
        out = {}
        for (kind, legs), members in groups.items():
            salts = jnp.array([zlib.crc32(name.encode()) & 0x7FFFFFFF for name, _ in members],
                              jnp.uint32)
            params = [jnp.array([getattr(d, p) for _, d in members])
                      for p in ("mean", "std", "low", "high")]
            values = jax.vmap(lambda salt, *p: sample_kind(
                kind, jax.random.fold_in(k, salt), (n_legs,) if legs else (), *p))(salts, *params)
            out.update({name: values[j] for j, (name, _) in enumerate(members)})
        return out

    return jax.vmap(one)(idx)


def scene_fields(spec: MonteCarloSpec, inputs: dict, count: int, n_legs: int) -> dict:
    """The ``Scene.batch`` fields [SI] of ``count`` samples with these dispersed ``inputs`` and
    the spec's fixed inputs (numpy or traced arrays alike)."""
    fields: dict = {}
    com = None
    for name, value in [*inputs.items(), *spec.fixed.items()]:
        target, to_si, comp = DISPERSIBLE[name]
        val = jnp.broadcast_to(jnp.asarray(value, dtype=jnp.float64) * to_si,
                               (count, n_legs) if comp == "legs" else (count,))
        if target == "com_offset":
            com = (jnp.zeros((count, 3)) if com is None else com).at[:, comp].set(val)
        else:
            fields[target] = val
    if com is not None:
        fields["com_offset"] = com
    if not fields:
        fields["drop_height"] = jnp.full(count, 0.2)
    return fields
