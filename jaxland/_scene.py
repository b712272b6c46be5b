"""Scenes: the touchdown conditions of one landing, as data (a pytree, so it vmaps).

World frame: z up, the ground plane through the origin (tilted by ``slope`` towards
``slope_direction``). Angles are radians and rates rad/s inside the code; the TOML scene file
and the CLI take degrees (``*_deg``, ``*_degps``). Body attitude is yaw-pitch-roll (z-y'-x'')
from the world frame; at zero yaw leg i points along azimuth i * 360 / n_legs deg.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._checks import check_int_size
from ._errors import ConfigError
from ._params import _f64, _opt_f64, concrete
from ._toml import read_toml, toml_value

__all__ = ["Scene", "load_scene", "scene_from_dict", "is_symmetric", "batch_axes"]


_DEG = math.pi / 180.0

class SceneField(NamedTuple):
    unit: str  # SI unit of the field
    doc: str
    lo: float  # envelope, SI
    hi: float
    toml: str  # TOML key (unit in the name)
    to_si: float  # TOML -> SI factor
    # an azimuth repeats every 2 pi: a statistic over it reads its sine and cosine, never the
    # angle as a line
    circular: bool = False


# Limits are our documented envelope: attitude within 30 deg (a steeper vehicle is not
# "landing"), rates within 5 rad/s, slopes within 30 deg.
SCENE_FIELDS = {
    "drop_height": SceneField("m", "clearance of the lowest foot above the ground at t = 0 "
                              "(on a slope: along the ground's normal)",
                              0.0, 50.0, "drop_height_m", 1.0),
    "sink_speed": SceneField("m/s", "downward speed at t = 0", 0.0, 30.0, "sink_speed_mps", 1.0),
    "horizontal_speed": SceneField("m/s", "horizontal speed at t = 0", 0.0, 30.0,
                                   "horizontal_speed_mps", 1.0),
    "heading": SceneField("rad", "direction of the horizontal velocity (azimuth from world x)",
                          -4 * math.pi, 4 * math.pi, "heading_deg", _DEG, circular=True),
    "roll": SceneField("rad", "body roll about x''", -30 * _DEG, 30 * _DEG, "roll_deg", _DEG),
    "pitch": SceneField("rad", "body pitch about y'", -30 * _DEG, 30 * _DEG, "pitch_deg", _DEG),
    "yaw": SceneField("rad", "body yaw about z", -4 * math.pi, 4 * math.pi, "yaw_deg", _DEG,
                      circular=True),
    "roll_rate": SceneField("rad/s", "body-frame angular rate about x", -5.0, 5.0,
                            "roll_rate_degps", _DEG),
    "pitch_rate": SceneField("rad/s", "body-frame angular rate about y", -5.0, 5.0,
                             "pitch_rate_degps", _DEG),
    "yaw_rate": SceneField("rad/s", "body-frame angular rate about z", -5.0, 5.0,
                           "yaw_rate_degps", _DEG),
    "slope": SceneField("rad", "ground slope", 0.0, 30 * _DEG, "slope_deg", _DEG),
    "slope_direction": SceneField("rad", "downhill direction of the slope (azimuth from world x)",
                                  -4 * math.pi, 4 * math.pi, "slope_direction_deg", _DEG,
                                  circular=True),
}
# Envelope of the optional scene fields, SI: friction within [0, 2], body mass within a factor 2
# either way, honeycomb scatter within a factor 5, centre-of-mass offset within +/-0.3 m.
OPTIONAL_LIMITS = {"friction": (0.0, 2.0), "mass_scale": (0.5, 2.0), "plateau_scale": (0.2, 5.0),
                   "com_offset": (-0.3, 0.3)}


_COM_OFFSET_RULE = (f"must be three finite numbers (x, y, z), each within "
                    f"+/-{OPTIONAL_LIMITS['com_offset'][1]:g} m")

# the unit a TOML key's suffix names, as a message prints it
_UNIT_OF_SUFFIX = {"m": "m", "mps": "m/s", "deg": "deg", "degps": "deg/s"}


def _number(name: str, default, optional: bool = False):
    """A Scene field converted to float64 (None stays None where ``optional``); a flag, a text
    or no number is refused by the field's name."""
    convert = _opt_f64 if optional else _f64
    return eqx.field(converter=functools.partial(convert, name=f"scene.{name}"),
                     default=default)


class Scene(eqx.Module):
    """Touchdown conditions of one landing (see ``SCENE_FIELDS`` for units and limits).

    ``Scene()`` is the paper's symmetric 0.2 m drop. ``friction`` overrides the vehicle's mu
    when given; ``plateau_scale`` (one entry per leg) scales both plateau forces of each leg
    (honeycomb scatter) when given; ``mass_scale`` scales the body mass and inertia (propellant
    left, payload); ``com_offset`` (3,) [m] moves the body's centre of mass from its geometric
    axis, in the body frame (3-D model). Left as None they cost nothing.
    """

    drop_height: jnp.ndarray = _number("drop_height", 0.2)
    sink_speed: jnp.ndarray = _number("sink_speed", 0.0)
    horizontal_speed: jnp.ndarray = _number("horizontal_speed", 0.0)
    heading: jnp.ndarray = _number("heading", 0.0)
    roll: jnp.ndarray = _number("roll", 0.0)
    pitch: jnp.ndarray = _number("pitch", 0.0)
    yaw: jnp.ndarray = _number("yaw", 0.0)
    roll_rate: jnp.ndarray = _number("roll_rate", 0.0)
    pitch_rate: jnp.ndarray = _number("pitch_rate", 0.0)
    yaw_rate: jnp.ndarray = _number("yaw_rate", 0.0)
    slope: jnp.ndarray = _number("slope", 0.0)
    slope_direction: jnp.ndarray = _number("slope_direction", 0.0)
    friction: jnp.ndarray | None = _number("friction", None, optional=True)
    # None (the default) means no scatter: static, so the honeycomb stays a compile-time constant
    # of the loop (runtime-valued parameters make XLA's CPU loop several times slower).
    plateau_scale: jnp.ndarray | None = _number("plateau_scale", None, optional=True)
    mass_scale: jnp.ndarray | None = _number("mass_scale", None, optional=True)
    com_offset: jnp.ndarray | None = _number("com_offset", None, optional=True)

    @classmethod
    def from_touchdown_speed(cls, speed_mps: float, **kwargs) -> Scene:
        """A scene that starts at touchdown with downward speed ``speed_mps`` [m/s]."""
        for name in ("drop_height", "sink_speed"):
            if name in kwargs:  # named, where Python's repeated-keyword TypeError names no rule
                raise ConfigError(name, kwargs[name], "is set by from_touchdown_speed (a "
                                  "touchdown: drop_height 0, sink_speed the speed given); "
                                  "for a release above the ground use jaxland.Scene")
        return cls(drop_height=0.0, sink_speed=speed_mps, **kwargs)

    @classmethod
    def batch(cls, **fields) -> Scene:
        """A batch of scenes: each given field an array over the batch (scalars broadcast to it);
        every other field keeps its single default value. ``plateau_scale`` takes shape
        (batch, n_legs). Run it with ``jaxland.landings`` or ``jax.vmap(..., in_axes=
        (batch_axes(batch),))``: fields left out stay unbatched, which keeps them compile-time
        constants (batched honeycomb parameters cost ~3x on CPU)."""
        vector = ("plateau_scale", "com_offset")
        for name, val in fields.items():
            most = 2 if name in vector else 1
            if val is not None and name in vector and np.ndim(val) == 0:
                raise ConfigError(f"scene.{name}", float(np.asarray(val)), "a batch gives "
                                  "one row per scene (shape (batch, n)), or one row for all "
                                  "(shape (n,)): one number has no components")
            if val is not None and np.ndim(val) > most:
                raise ConfigError(f"scene.{name}", np.asarray(val).tolist(), "a batch gives "
                                  + ("one row per scene (shape (batch, n))" if most == 2 else
                                     "one value per scene (a 1-D array)")
                                  + f"; this has shape {np.shape(val)}")
        sizes = {np.shape(v)[0] for k, v in fields.items()
                 if v is not None and np.ndim(v) > (1 if k in vector else 0)}
        if len(sizes) != 1:
            raise ConfigError("Scene.batch", sorted(sizes),
                              "give at least one batched field, all of the same length "
                              "(plateau_scale and com_offset batch as (batch, n) arrays)")
        (n,) = sizes
        out = {}
        for name, val in fields.items():
            if val is None:
                out[name] = None
                continue
            val = _f64(val, f"scene.{name}")  # refused by name before it is broadcast
            if name in vector:
                out[name] = jnp.broadcast_to(val, (n, val.shape[-1]))
            else:
                out[name] = jnp.broadcast_to(val, (n,))
        return cls(**out)

    def fall_time(self, g=9.81):
        """Time [s] of the free fall from the scene's clearance to first contact, the attitude
        held: (sqrt(v0^2 + 2 g h) - v0) / g on level ground. On a slope the clearance is
        measured along the ground normal n and the body falls vertically while its horizontal
        motion moves it across the slope, so the clearance h + a t - (v0 t + g t^2 / 2) n_z
        (a = horizontal velocity . n) reaches 0 at this t*."""
        v0, h = self.sink_speed, self.drop_height
        nz = jnp.cos(self.slope)
        a = self.horizontal_speed * jnp.sin(self.slope) * jnp.cos(self.heading
                                                                  - self.slope_direction)
        b = v0 * nz - a
        return (jnp.sqrt(b * b + 2.0 * g * nz * h) - b) / (g * nz)

    def turning(self):
        """True (a jnp bool, per landing) where the body turns at release (a rate given): its
        attitude then changes in the free fall, which ``fall_time`` holds."""
        return (self.roll_rate != 0.0) | (self.pitch_rate != 0.0) | (self.yaw_rate != 0.0)

    def touchdown_speed(self, g=9.81):
        """Vertical speed at first contact [m/s] of the free fall from the scene's clearance
        (``fall_time``, the attitude held: no body rates): sqrt(v0^2 + 2 g h) on level
        ground, v0 + g t* on a slope."""
        v0, h = self.sink_speed, self.drop_height
        level = jnp.sqrt(v0**2 + 2.0 * g * h)
        return jnp.where(self.slope == 0.0, level, v0 + g * self.fall_time(g))

    def inside_envelope(self):
        """True (a jnp bool, also under jit and vmap) if every field lies in the documented
        envelope that ``validate`` checks, finite; a landing outside it carries
        ``Result.OUTSIDE_ENVELOPE``."""
        ok = jnp.ones((), bool)
        for name, field in SCENE_FIELDS.items():
            x = jnp.asarray(getattr(self, name))
            ok = ok & jnp.all(jnp.isfinite(x) & (x >= field.lo) & (x <= field.hi))
        for name, (lo, hi) in OPTIONAL_LIMITS.items():
            x = getattr(self, name)
            if x is not None:
                x = jnp.asarray(x)
                ok = ok & jnp.all(jnp.isfinite(x) & (x >= lo) & (x <= hi))
        return ok

    def symmetric(self):
        """``is_symmetric`` as a jnp bool, also under jit and vmap: a quarter-model landing of
        an asymmetric scene carries ``Result.OUTSIDE_ENVELOPE`` (that model cannot represent
        it)."""
        return _symmetric(self, jnp)

    def check_shapes(self, n_legs: int | None = None) -> Scene:
        """Refuse a ``com_offset`` without its three components and a ``plateau_scale``
        without one entry per leg (of ``n_legs``, where given). Shapes are known under jit and
        vmap too, where a wrong one fails deep inside the landing."""
        for name, field, size, rule in (
                ("com_offset", "scene.com_offset_m", 3, _COM_OFFSET_RULE),
                ("plateau_scale", "scene.plateau_scale", n_legs,
                 f"must have one entry per leg ({n_legs})")):
            val = getattr(self, name)
            shape = np.shape(val)
            if val is None or size is None or (shape and shape[-1] == size):
                continue
            arr = concrete(val)
            raise ConfigError(field, shape if arr is None else arr.tolist(), rule)
        return self

    def check_one(self) -> Scene:
        """Refuse, for one landing, a field holding several values: each of ``SCENE_FIELDS``,
        the friction and the mass scale one number, the plateau scale one per leg at most,
        the centre-of-mass offset one vector: a batch's shapes would otherwise fail deep inside
        ``landing``, or, for the friction, run silently as one value per leg. Shapes are known
        under jit."""
        one = {name: (f"scene.{f.toml}", 0) for name, f in SCENE_FIELDS.items()}
        one.update(friction=("scene.friction", 0), mass_scale=("scene.mass_scale", 0),
                   plateau_scale=("scene.plateau_scale", 1),
                   com_offset=("scene.com_offset_m", 1))
        for name, (field, ndim) in one.items():
            val = getattr(self, name)
            if val is not None and np.ndim(val) > ndim:
                what = ("one number" if ndim == 0 else "one value per leg"
                        if name == "plateau_scale" else "one vector")
                raise ConfigError(field, f"shape {np.shape(val)}", f"must be {what} for one "
                                  "landing (a Scene.batch runs with jaxland.landings)")
        return self

    def validate(self, n_legs: int | None = None) -> Scene:
        """Refuse scenes outside the documented envelope, naming field, value and rule."""
        for name, f in SCENE_FIELDS.items():
            arr = concrete(getattr(self, name))
            if arr is None:
                continue
            bad = ~np.isfinite(arr) | (arr < f.lo) | (arr > f.hi)
            if np.any(bad):
                shown = float(arr[bad].flat[0]) / f.to_si
                raise ConfigError(f"scene.{f.toml}", shown, f"must be finite and in "
                                  f"[{f.lo / f.to_si:.4g}, {f.hi / f.to_si:.4g}] "
                                  f"{_UNIT_OF_SUFFIX[f.toml.rsplit('_', 1)[-1]]}")
        fr = concrete(self.friction)
        lo, hi = OPTIONAL_LIMITS["friction"]
        if fr is not None and np.any(~np.isfinite(fr) | (fr < lo) | (fr > hi)):
            raise ConfigError("scene.friction", float(np.ravel(fr)[0]),
                              f"must be finite and in [{lo:g}, {hi:g}]")
        ms = concrete(self.mass_scale)
        lo, hi = OPTIONAL_LIMITS["mass_scale"]
        if ms is not None and np.any(~np.isfinite(ms) | (ms < lo) | (ms > hi)):
            raise ConfigError("scene.mass_scale", float(np.ravel(ms)[0]),
                              f"must be finite and in [{lo:g}, {hi:g}]")
        self.check_shapes(n_legs)
        co = concrete(self.com_offset)
        lo, hi = OPTIONAL_LIMITS["com_offset"]
        if co is not None and np.any(~np.isfinite(co) | (co < lo) | (co > hi)):
            raise ConfigError("scene.com_offset_m", co.tolist(), _COM_OFFSET_RULE)
        ps = concrete(self.plateau_scale)
        if ps is not None:
            lo, hi = OPTIONAL_LIMITS["plateau_scale"]
            if np.any(~np.isfinite(ps) | (ps < lo) | (ps > hi)):
                raise ConfigError("scene.plateau_scale", ps.tolist(),
                                  f"every entry must be finite and in [{lo:g}, {hi:g}]")
        return self


def batch_axes(scene: Scene) -> Scene:
    """``in_axes`` for ``jax.vmap`` over a batch from ``Scene.batch``: 0 for the batched fields,
    None for the rest."""
    def axis(name, val):
        if val is None:
            return None
        base = 1 if name in ("plateau_scale", "com_offset") else 0
        return 0 if np.ndim(val) > base else None

    return _axes_scene(
        {name: axis(name, getattr(scene, name)) for name in scene.__dataclass_fields__})


def _axes_scene(axes: dict) -> Scene:
    obj = object.__new__(Scene)
    for name, val in axes.items():
        object.__setattr__(obj, name, val)
    return obj


# the fields a symmetric vertical drop holds at 0 (com_offset: where given); its plateau
# scale must also be the same on every leg
ZERO_IN_A_SYMMETRIC_DROP = ("horizontal_speed", "roll", "pitch", "roll_rate", "pitch_rate",
                            "yaw_rate", "slope", "com_offset")


def _symmetric(scene: Scene, xp):
    """Whether every landing in ``scene`` is a symmetric vertical drop, with the array module
    ``xp`` (numpy on concrete values, jax.numpy under jit): the one rule ``is_symmetric`` and
    ``Scene.symmetric`` share."""
    ok = xp.all(xp.stack([xp.all(xp.asarray(getattr(scene, name)) == 0.0) for name in
                          ZERO_IN_A_SYMMETRIC_DROP if getattr(scene, name) is not None]))
    if scene.plateau_scale is not None:
        ps = xp.asarray(scene.plateau_scale)
        ok = ok & xp.all(ps == ps[..., :1])
    return ok


def is_symmetric(scene: Scene) -> bool:
    """True if every landing in ``scene`` (a batch allowed) is a symmetric vertical drop, so the
    quarter model represents it exactly: no horizontal speed, level attitude (yaw is free), no
    angular rate, level ground, the same honeycomb in every leg. Needs concrete values
    (``Scene.symmetric`` is the same test under jit)."""
    return bool(_symmetric(scene, np))


def scene_from_dict(data: dict) -> Scene:
    """Scene from a TOML-shaped table (keys with units, angles in degrees); validated."""
    known = {v.toml: k for k, v in SCENE_FIELDS.items()}
    kwargs = {}
    for key, val in data.items():
        for v in val if isinstance(val, list) else [val]:  # a list: each entry
            check_int_size(f"scene.{key}", v)
        if key in ("friction", "plateau_scale", "mass_scale", "com_offset_m"):
            kwargs["com_offset" if key == "com_offset_m" else key] = val
            continue
        if key not in known:
            raise ConfigError(f"scene.{key}", val, "unknown key; known: "
                              + ", ".join([*known, "friction", "plateau_scale", "mass_scale",
                                           "com_offset_m"]))
        if isinstance(val, bool) or not isinstance(val, (int, float)):
            raise ConfigError(f"scene.{key}", val, "must be a number")
        kwargs[known[key]] = float(val) * SCENE_FIELDS[known[key]].to_si
    if "plateau_scale" in kwargs:
        ps = kwargs["plateau_scale"]
        if not isinstance(ps, list) or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in ps):
            raise ConfigError("scene.plateau_scale", ps, "must be a list of numbers, one per leg")
    for key in ("friction", "mass_scale"):
        if key in kwargs and (isinstance(kwargs[key], bool)
                              or not isinstance(kwargs[key], (int, float))):
            raise ConfigError(f"scene.{key}", kwargs[key], "must be a number")
    if "com_offset" in kwargs:
        co = kwargs["com_offset"]
        if not isinstance(co, list) or len(co) != 3 or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in co):
            raise ConfigError("scene.com_offset_m", co, "must be a list of three numbers (x, y, z)")
    return Scene(**kwargs).validate()


def scene_to_toml(scene: Scene) -> str:
    """One scene as a ``[scene]`` table with every field (``scene_from_dict`` reads it back to
    the same scene): what a run's output folder records."""
    lines = ["# jaxland scene (units in the keys; angles in degrees)", "[scene]"]
    for name, f in SCENE_FIELDS.items():
        val = float(np.asarray(getattr(scene, name))) / f.to_si
        lines.append(f"{f.toml} = {toml_value(val)}  # {f.doc}")
    for name, key in (("friction", "friction"), ("mass_scale", "mass_scale"),
                      ("plateau_scale", "plateau_scale"), ("com_offset", "com_offset_m")):
        val = getattr(scene, name)
        if val is not None:
            lines.append(f"{key} = {toml_value(np.asarray(val, dtype=float).tolist())}")
    return "\n".join(lines) + "\n"


def read_scene_table(path, what: str = "scene") -> dict:
    """The scene table of a scene TOML file: its ``[scene]`` table (or its top-level keys).
    Refusals name the file by ``what`` (the flag that gave it). A file that sets no key
    (empty, comments, an empty ``[scene]``) is refused: every key left out takes its default,
    so it would run, silently, the default scene."""
    data = read_toml(path, what)
    if "scene" in data and len(data) > 1:
        extra = sorted(set(data) - {"scene"})[0]
        if not isinstance(data[extra], dict):  # a key above [scene]: it belongs inside it
            raise ConfigError(f"{what} {path}: {extra}", data[extra],
                              "stands outside the [scene] table: a file with a [scene] table "
                              "holds its keys inside it")
        raise ConfigError(f"{what} {path}: {extra}", "<table>",
                          "a scene file holds the [scene] table only (vehicle parameters "
                          "belong in --config; friction = ... inside [scene] overrides mu)")
    table = data.get("scene", data)
    if not isinstance(table, dict):
        raise ConfigError(f"{what} {path}: scene", table,
                          "must be a table ([scene] with its keys)")
    if not table:
        raise ConfigError(what, str(path), "sets no scene key, and would run the default scene "
                          "(every key left out takes its default: the 0.2 m drop); give the "
                          "scene's values (docs/formats.md, Scene)")
    return dict(table)


def load_scene(path) -> Scene:
    """Load a scene TOML file: a ``[scene]`` table (or top-level keys); see
    ``read_scene_table`` for what is refused."""
    return scene_from_dict(read_scene_table(path))
