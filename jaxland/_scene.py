"""Scenes: the touchdown conditions of one landing, as data (a pytree, so it vmaps)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._errors import ConfigError

__all__ = ["Scene"]


def _f64(x):
    return jnp.asarray(x, dtype=jnp.float64)


class Scene(eqx.Module):
    """Touchdown conditions of a symmetric vertical landing.

    ``drop_height`` is the clearance of the feet above the ground at t = 0 [m] (the paper's
    H_height = 0.2 m), ``sink_speed`` the downward speed at t = 0 [m/s]. A scene given by its
    touchdown speed starts with the feet on the ground: ``Scene.from_touchdown_speed(v)``.
    """

    drop_height: jnp.ndarray = eqx.field(converter=_f64, default=0.2)
    sink_speed: jnp.ndarray = eqx.field(converter=_f64, default=0.0)

    @classmethod
    def from_touchdown_speed(cls, speed_mps: float) -> Scene:
        """A scene that starts at touchdown with downward speed ``speed_mps`` [m/s]."""
        return cls(drop_height=0.0, sink_speed=speed_mps)

    def touchdown_speed(self, g=9.81):
        """Vertical speed at first contact [m/s], sqrt(v0^2 + 2 g h)."""
        return jnp.sqrt(self.sink_speed**2 + 2.0 * g * self.drop_height)

    def validate(self) -> Scene:
        """Refuse non-physical scenes with a message naming field, value and rule."""
        for name, lo, hi in (("drop_height", 0.0, 50.0), ("sink_speed", 0.0, 30.0)):
            val = getattr(self, name)
            if isinstance(val, jnp.ndarray) and not _is_concrete(val):
                continue
            arr = np.asarray(val, dtype=float)
            bad = ~np.isfinite(arr) | (arr < lo) | (arr > hi)
            if np.any(bad):
                v = arr[bad].flat[0]
                unit = "m" if name == "drop_height" else "m/s"
                raise ConfigError(f"scene.{name}", v, f"must be finite and in [{lo}, {hi}] {unit}")
        return self


def _is_concrete(x) -> bool:
    try:
        np.asarray(x)
        return True
    except Exception:  # a tracer under jit/vmap/grad
        return False


