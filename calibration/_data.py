"""Drop-test data: CSV traces plus a metadata TOML, validated, then preprocessed.

A drop test is two files side by side:

* ``NAME.csv``: a header naming each column with its unit, then one row per sample.
  ``time_s`` is required; any non-empty subset of the channels below may follow:

  ===================  =====  ===========================================================
  column               unit   model quantity (quarter model)
  ===================  =====  ===========================================================
  ``normal_force_N``   N      ``normal_force_N``: ground reaction on the instrumented foot
  ``buffer_force_N``   N      ``strut_force_N``: strut load cell (honeycomb + structural
                              damping + top-out stop)
  ``stroke_m``         m      ``stroke_m``: buffer stroke, compression positive
  ``body_accel_mps2``  m/s^2  ``body_az_mps2``: kinematic vertical acceleration of the body
                              (-g in free fall, not an accelerometer's specific force)
  ===================  =====  ===========================================================

  Columns in other units are converted where the conversion is unambiguous, and each
  conversion is logged (``DropTest.unit_conversions``, in the fit report): ``time_ms``,
  ``normal_force_kN``, ``buffer_force_kN``, ``stroke_mm``, ``body_accel_g`` (standard gravity,
  9.80665 m/s^2 per g). An accelerometer's specific force (0 in free fall, +1 g at rest) needs
  no flag: the pre-touchdown offset (step 2 below) removes its +g and leaves the kinematic
  acceleration, as long as the record holds some free fall before touchdown. Anything else
  (no unit, an unknown unit) is refused by name.

  Several instrumented legs: the same channels prefixed with the leg, ``leg2_stroke_m``,
  ``leg0_normal_force_kN`` (one series per leg and channel; a column without a prefix sits on
  ``sensor_leg``). A drop test is a symmetric vertical drop, so every leg follows the same
  quarter model: each leg's series is another measurement of it, with its own offset and
  noise (leg-to-leg differences, e.g. honeycomb scatter, show in the per-series residuals).
  The body acceleration belongs to the body and takes no leg prefix.

* ``NAME.toml``: a ``[drop_test]`` table (see ``META_KEYS``) with the drop height (or touchdown
  speed), the sample rate, the instrumented leg and the vehicle configuration; optionally the
  record's touchdown or release time, what the accelerometer measures, and a CFC filter.

Preprocessing (done on load, stored on the ``DropTest``; README of ``data/`` and the report
document it):

1. **Touchdown** is detected from the force onset (normal force, else buffer force, else body
   acceleration, else stroke): the first sample above ``baseline + max(8 sigma_hp, 5 % of the
   channel's rise)`` that stays above it for ``ONSET_PERSIST_S`` (at least 3 samples; the
   rise too is the largest level held that long, so a one-sample glitch sets neither), then
   extrapolated back along the rising edge to the baseline (a stroke, which grows from
   rest, first back along its samples ``STROKE_ONSET_SIGMAS`` sigma_hp from its level just
   before the rise: ``_stroke_onset``). Or it is
   given: ``touchdown_time_s`` in the metadata (a record that starts at touchdown). The fit
   refines it as a parameter per drop (``t0``). With ``release_time_s`` the free fall from
   release to touchdown is checked against the drop height (``FREE_FALL_REL``).
2. **Offsets** per channel are the mean of the pre-touchdown segment (after the release, when
   it is given) minus the free-fall value the model has there (0 for forces and stroke, -g for
   the body acceleration). This removes e.g. a stroke sensor's zero error. A record with fewer
   than ``MIN_PRE_SAMPLES`` before touchdown (one that starts at touchdown) keeps its zero: the
   offsets are taken as 0, and say so (``offset_source``).
3. **Noise** per channel is the standard deviation of the pre-touchdown segment when it has at
   least ``MIN_NOISE_SAMPLES`` samples, else a high-pass estimate (median absolute second
   difference / 0.6745 / sqrt(6), robust to the signal) over the whole record. A floor of
   ``NOISE_FLOOR_REL`` of the channel's range keeps noise-free (synthetic) data well-posed.
   The fit weights each channel by 1/noise^2.
"""

from __future__ import annotations

import csv
import io
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import jaxland as jl

__all__ = ["CHANNELS", "DropTest", "load_drop_test", "load_drop_tests", "META_KEYS",
           "base_channel", "leg_of"]

# channel column -> (unit, quarter-model trajectory column, free-fall value before touchdown
# (None: -g), description)
CHANNELS = {
    "normal_force_N": ("N", "normal_force_N", 0.0, "ground normal force on the foot"),
    "buffer_force_N": ("N", "strut_force_N", 0.0, "strut (buffer) load cell force"),
    "stroke_m": ("m", "stroke_m", 0.0, "buffer stroke, compression positive"),
    "body_accel_mps2": ("m/s^2", "body_az_mps2", None,
                        "kinematic vertical body acceleration (-g in free fall)"),
}
TIME = "time_s"
# What each channel's base name must be suffixed with, and units people write instead.
_UNIT_SUFFIX = {"time": "s", "normal_force": "N", "buffer_force": "N", "stroke": "m",
                "body_accel": "mps2"}
_UNIT_WORDS = {"s": "s", "N": "N", "m": "m", "mps2": "m/s^2"}
STANDARD_GRAVITY = 9.80665  # m/s^2 per g (ISO 80000-3)
# unambiguous conversions: column -> (SI column, factor to SI)
CONVERSIONS = {
    "time_ms": (TIME, 1e-3),
    "normal_force_kN": ("normal_force_N", 1e3),
    "buffer_force_kN": ("buffer_force_N", 1e3),
    "stroke_mm": ("stroke_m", 1e-3),
    "body_accel_g": ("body_accel_mps2", STANDARD_GRAVITY),
}

LEG_COLUMN = re.compile(r"^leg(\d+)_(.+)$")  # leg2_stroke_m: the stroke on leg 2
ACCEL_KINDS = ("kinematic", "specific_force")

# the largest gain uncertainty taken: beyond it a channel's calibration is no calibration
GAIN_UNCERTAINTY_MAX = 0.2
META_KEYS = {
    "data_file": "CSV file with the traces, relative to this file (default: same name, .csv)",
    "drop_height_m": "lowest foot's clearance above the ground at release [m], in [0, 50]",
    "sink_speed_mps": "downward speed at release [m/s], in [0, 30] (with drop_height_m)",
    "touchdown_speed_mps": "downward speed at touchdown [m/s], in (0, 30] (instead of "
                           "drop_height_m)",
    "sample_rate_Hz": "sample rate of the traces [Hz]; must match the time column within 1 %, "
                      "which must be sampled uniformly (INTERVAL_REL, GRID_REL)",
    "sensor_leg": "index of the leg (and foot) the sensors sit on, in [0, n_legs)",
    "vehicle_config": "vehicle TOML, relative to this file (default: the paper vehicle)",
    "touchdown_time_s": "time of touchdown on the record's time axis [s] (default: detected "
                        "from the force onset); for records that start at touchdown",
    "release_time_s": "time of release on the record's time axis [s], may precede the record "
                      "(a record that starts mid-fall); the free fall to touchdown is checked "
                      "against drop_height_m",
    "body_accel_kind": "what the body acceleration column measures: 'kinematic' (-g in free "
                       "fall) or 'specific_force' (an accelerometer: 0 in free fall, +1 g at "
                       "rest); default: read from the pre-touchdown level",
    "filter_cfc": "SAE J211 channel frequency class applied alike to data and model in the "
                  "misfit: 60, 180, 600 or 1000 for every channel, or a table {column = class}",
    "filter_data_prefiltered": "true when the record was already filtered with filter_cfc by "
                               "the lab: then only the model is filtered (default false)",
    "gain_uncertainty_rel": "standard uncertainty of each channel's gain, relative (its "
                            "calibration's: 0.005 for 0.5 %), one number for every channel or a "
                            f"table {{column = value}}, each in [0, {GAIN_UNCERTAINTY_MAX:g}]; the "
                            "fit's intervals carry it (default: the gains are taken as exact)",
    "synthetic": "true for generated data (e.g. by calibration.virtual_rig)",
    "description": "free text",
}
_OPTIONAL_TABLES = ("synthetic_rig",)  # generator settings, informational only

MIN_PRE_SAMPLES = 10  # samples before touchdown (offsets, and a touchdown that is in the record)
ONSET_PERSIST_S = 1e-3  # s: an onset holds above its threshold this long (>= 3 samples)
STROKE_ONSET_SIGMAS = 4.0  # a stroke's onset: where it leaves its noise (high-pass sigmas)
STROKE_ONSET_REACH = 3.0  # how far back a stroke's rise may begin, in straight-line times
MIN_NOISE_SAMPLES = 50  # pre-touchdown samples for a noise estimate from that segment
MIN_AFTER_S = 0.05  # s of record after touchdown
MIN_SAMPLES = 50
# a drop's impact lasts tens of ms (50-70 ms of crush on the bundled 0.15-0.3 m drops): a
# record sampled slower than this holds a few samples of it at most (times in ms under a
# time_s header read 1000 times slower: 5 Hz for a 5 kHz record); and a drop record spans
# seconds, so one longer than this is refused (fit and predict simulate all of it after
# touchdown, and the simulator stops at 100 s)
MIN_SAMPLE_RATE_HZ = 100.0
MAX_RECORD_S = 60.0
# the CFC filter, the noise estimates and the residuals' autocorrelation (error bars) count
# samples, not seconds: a record must be sampled uniformly. Every interval between samples
# must lie within INTERVAL_REL of 1/sample_rate_Hz (one dropped sample doubles an interval;
# times printed to 7 digits over 60 s at 10 kHz, or held in float32 at 50 kHz, move one by
# 10-20 %), and every sample within GRID_REL intervals of the uniform grid fitted through
# them (a rate that changes along the record, each interval passing alone); a clock whose
# rate is off by a constant factor is the sample rate's 1 % rule's
INTERVAL_REL = 0.25
GRID_REL = 0.5
NOISE_FLOOR_REL = 1e-4  # noise floor, fraction of the channel's range (noise-free data)
# the drop height that the free fall from release to touchdown implies must match the
# metadata's within FREE_FALL_REL of it or FREE_FALL_ABS_M, whichever is larger (a release
# mechanism's delay of a few ms is 1-3 % of the height at 0.2 m)
FREE_FALL_REL = 0.05
FREE_FALL_ABS_M = 2e-3
# a body acceleration swings through the impact by 0.5-1 of a force channel's swing over the
# leg's mass (bundled records, rig drops of 0.01-1 m); in g by a tenth of that: refused below
ACCEL_SWING_MIN = 0.25
# a stroke beyond this many times the honeycomb's crush length x_L4: the bottoming stop ends
# the stroke there, so it is a unit (inches: 39 times, cm: 100 times) or the wrong vehicle
STROKE_PAST_CRUSH = 2.0
# ... and, read from a g column, above this many times the largest such swing (m/s^2 under a
# body_accel_g header reads 9.81 times too large: 6 to 9 times it)
ACCEL_SWING_MAX = 4.0
# the body acceleration follows the force channels through the impact (correlation 0.95 to
# 0.995 on the bundled records): below minus this, its sign is flipped
ACCEL_ANTICORRELATION = 0.5
# a force channel's peak above this many times what the vehicle can put on a leg in the drop
# (DropTest.impact_bounds' force_max_N), or a stroke read from a mm column under 1 / this of
# the least the drop's energy needs (stroke_min_m), is refused: the bundled records reach at
# most 0.34 of the first and 1.66 to 1.99 times the second (tests/test_calibration.py), so
# only a unit a thousand times off is refused
PLAUSIBLE_FACTOR = 10.0
_ONSET_ORDER = ("normal_force_N", "buffer_force_N", "body_accel_mps2", "stroke_m")


def _err(field_, value, rule):
    return jl.ConfigError(field_, value, rule)


def base_channel(col: str) -> str:
    """The channel of a data column: ``leg2_stroke_m`` -> ``stroke_m``."""
    m = LEG_COLUMN.match(col)
    return m.group(2) if m else col


def leg_of(col: str, sensor_leg: int = 0) -> int:
    """The leg a data column sits on (``sensor_leg`` for a column without a leg prefix)."""
    m = LEG_COLUMN.match(col)
    return int(m.group(1)) if m else int(sensor_leg)


@dataclass
class DropTest:
    """One drop test: validated traces, metadata and preprocessing.

    ``channels`` maps column names (``stroke_m``, ``leg2_stroke_m`` ...) to raw samples;
    ``corrected`` gives them with the offsets removed. Times are the record's own (``time_s``);
    ``touchdown_time_s`` is the detected (or given) touchdown on that axis. ``filters`` maps a
    column to its SAE J211 class (``calibration._filter``), applied alike to data and model in
    the misfit.
    """

    name: str
    time_s: np.ndarray
    channels: dict
    touchdown_speed_mps: float
    sample_rate_Hz: float
    vehicle: jl.Vehicle = field(repr=False)
    drop_height_m: float | None = None
    sink_speed_mps: float = 0.0
    sensor_leg: int = 0
    vehicle_config: str | None = None
    synthetic: bool = False
    description: str = ""
    source: str = "<arrays>"
    touchdown_time_s: float = float("nan")
    onset_channel: str = ""
    offsets: dict = field(default_factory=dict)
    offset_source: str = ""
    offset_samples: int = 0  # free-fall samples each offset is the mean of (0: no offset)
    noise_std: dict = field(default_factory=dict)
    noise_source: dict = field(default_factory=dict)
    unit_conversions: dict = field(default_factory=dict)
    files: tuple = ()  # the files its metadata names: itself, the traces, the vehicle's
    touchdown_given_s: float | None = None
    release_time_s: float | None = None
    free_fall: dict = field(default_factory=dict)
    body_accel_kind: str | None = None
    filters: dict = field(default_factory=dict)
    filter_data_prefiltered: bool = False
    # {column: standard uncertainty of its gain, relative}; a column left out is exact
    gain_uncertainty_rel: dict = field(default_factory=dict)

    @classmethod
    def from_arrays(cls, time_s, channels: dict, *, sample_rate_Hz=None, drop_height_m=None,
                    sink_speed_mps=None, touchdown_speed_mps=None, sensor_leg=0, vehicle=None,
                    vehicle_config=None, name="drop", synthetic=False, description="",
                    source="<arrays>", touchdown_time_s=None, release_time_s=None,
                    body_accel_kind=None, filter_cfc=None,
                    filter_data_prefiltered=False, gain_uncertainty_rel=None) -> DropTest:
        """Validate and preprocess traces given as arrays (what ``load_drop_test`` does after
        reading the files). Raises ``jaxland.ConfigError`` naming field, value and rule.
        The keywords are the metadata keys (``META_KEYS``) in SI units."""
        vehicle = jl.paper_vehicle() if vehicle is None else vehicle
        time_s = _as_trace(TIME, time_s)
        if not channels:
            raise _err("columns", TIME, "need at least one data channel besides time_s; known: "
                       + ", ".join(CHANNELS))
        n_legs = vehicle.n_legs
        if isinstance(sensor_leg, bool) or not isinstance(sensor_leg, (int, np.integer)) \
                or not 0 <= int(sensor_leg) < n_legs:
            raise _err("sensor_leg", sensor_leg, f"must be an integer in [0, {n_legs}) "
                       "(the vehicle's legs)")
        chans, conversions, seen = {}, {}, {}
        for col, vals in channels.items():
            _check_column_name(col)
            m = LEG_COLUMN.match(col)
            prefix, base = (f"leg{m.group(1)}_", m.group(2)) if m else ("", col)
            if m and not int(m.group(1)) < n_legs:
                raise _err(f"column {col!r}", int(m.group(1)), f"leg index must be in [0, "
                           f"{n_legs}) (the vehicle's legs)")
            if base in CONVERSIONS:  # an unambiguous unit: convert, and log it
                si, factor = CONVERSIONS[base]
                conversions[col] = f"{col} -> {prefix}{si} (x {factor:g})"
                vals, col = _as_trace(col, vals) * factor, prefix + si
            # one series per leg and channel: leg{sensor_leg}_x is the same series as x
            key = (leg_of(col, sensor_leg), base_channel(col))
            if key in seen:
                raise _err(f"column {col!r}", col, f"given twice: leg {key[0]}'s "
                           f"{key[1]} is also column {seen[key]!r} (a column without a leg "
                           f"prefix sits on sensor_leg = {int(sensor_leg)})")
            seen[key] = col
            chans[col] = _as_trace(col, vals)
            if chans[col].shape != time_s.shape:
                raise _err(col, f"{chans[col].size} samples",
                           f"must have as many samples as time_s ({time_s.size})")
        _check_time(time_s, sample_rate_Hz)
        g = float(vehicle.g)
        v_td, h, v0 = _touchdown_speed(drop_height_m, sink_speed_mps, touchdown_speed_mps, g)
        if body_accel_kind is not None and body_accel_kind not in ACCEL_KINDS:
            raise _err("body_accel_kind", body_accel_kind, "must be one of "
                       + ", ".join(ACCEL_KINDS))
        if body_accel_kind == "specific_force":
            acc = "body_accel_mps2"
            if acc in chans:
                chans[acc] = chans[acc] - g
                conversions[acc + " (specific force)"] = (
                    f"{acc}: specific force -> kinematic acceleration (- g = {g:g} m/s^2)")
        for key, val in (("touchdown_time_s", touchdown_time_s),
                         ("release_time_s", release_time_s)):
            if val is not None and (isinstance(val, bool) or not isinstance(val, (int, float))
                                    or not math.isfinite(val)):
                raise _err(key, val, "must be a finite number [s] on the record's time axis")
        if release_time_s is not None and h is None:
            raise _err("release_time_s", release_time_s, "needs drop_height_m (the free fall "
                       "from release is checked against the drop height)")
        filters = _filters(filter_cfc, chans, float(sample_rate_Hz))
        gains = _gain_uncertainty(gain_uncertainty_rel, chans)
        if not isinstance(filter_data_prefiltered, bool):
            raise _err("filter_data_prefiltered", filter_data_prefiltered, "must be true or "
                       "false")
        if filter_data_prefiltered and not filters:
            raise _err("filter_data_prefiltered", True, "needs filter_cfc (the class the lab "
                       "filtered the record with)")
        drop = cls(name=name, time_s=time_s, channels=chans, touchdown_speed_mps=v_td,
                   sample_rate_Hz=float(sample_rate_Hz), vehicle=vehicle, drop_height_m=h,
                   sink_speed_mps=v0, sensor_leg=int(sensor_leg), vehicle_config=vehicle_config,
                   synthetic=bool(synthetic), description=str(description), source=source,
                   unit_conversions=conversions,
                   touchdown_given_s=None if touchdown_time_s is None else float(
                       touchdown_time_s),
                   release_time_s=None if release_time_s is None else float(release_time_s),
                   body_accel_kind=body_accel_kind, filters=filters,
                   filter_data_prefiltered=bool(filter_data_prefiltered),
                   gain_uncertainty_rel=gains)
        drop._preprocess()
        return drop

    # ------------------------------------------------------------------ preprocessing
    def _detect_touchdown(self) -> tuple[float, str]:
        t = self.time_s
        onset = min(self.channels, key=lambda c: (_ONSET_ORDER.index(base_channel(c)),
                                                   leg_of(c, self.sensor_leg)))
        y = self.channels[onset]
        base = _start_level(y)
        sig = _highpass_noise(y)
        # an impact holds its level; a glitch (a trigger spike, a dropped sample) does not,
        # and taken as the onset (or as the rise) it put touchdown 20 ms early in one record:
        # the level each sample holds for the next ONSET_PERSIST_S
        persist = max(3, math.ceil(ONSET_PERSIST_S * self.sample_rate_Hz))
        dev = np.abs(y - base)
        held = (np.lib.stride_tricks.sliding_window_view(dev, persist).min(axis=1)
                if len(y) >= persist else np.zeros(0))
        rise = float(np.max(held)) if held.size else 0.0
        thresh = max(8.0 * sig, 0.05 * rise)
        above = np.nonzero(held > thresh)[0]
        if rise <= 0.0 or above.size == 0 or rise < 20.0 * sig:
            raise _err(f"{self.source}: {onset}", f"rise {rise:.4g}",
                       f"no touchdown found: the channel never rises clearly above its "
                       f"starting level (noise {sig:.3g}); is this a drop test?")
        i_c = int(above[0])
        if i_c < MIN_PRE_SAMPLES:
            raise _err(f"{self.source}: touchdown", f"sample {i_c}",
                       f"no touchdown found inside the record: the {onset} onset is at the "
                       f"start; need >= {MIN_PRE_SAMPLES} samples before touchdown (to set the "
                       "sensor offsets), or give drop_test.touchdown_time_s for a record that "
                       "starts at touchdown")
        if base_channel(onset) == "stroke_m":
            i_c, base = _stroke_onset(y, i_c, base, sig)
        # back along the rising edge (the first two samples past it) to the level before it
        y1, y2 = abs(y[i_c] - base), abs(y[min(i_c + 1, len(y) - 1)] - base)
        slope = (y2 - y1) / (t[i_c + 1] - t[i_c]) if i_c + 1 < len(t) else 0.0
        t0 = t[i_c] - y1 / slope if slope > 0 else t[i_c - 1]
        return float(min(max(t0, t[i_c - 1] - (t[i_c] - t[i_c - 1])), t[i_c])), onset

    def _preprocess(self) -> None:
        t = self.time_s
        dt = 1.0 / self.sample_rate_Hz
        if self.touchdown_given_s is not None:
            t0, onset = self.touchdown_given_s, "metadata (touchdown_time_s)"
            if not t[0] - dt <= t0 <= t[-1]:
                raise _err("touchdown_time_s", t0, f"must lie in the record [{t[0]:.6g}, "
                           f"{t[-1]:.6g}] s (or one sample before its start)")
        else:
            t0, onset = self._detect_touchdown()
        if t[-1] - t0 < MIN_AFTER_S or len(t) < MIN_SAMPLES:
            raise _err(f"{self.source}: time_s", f"{t[-1] - t0:.4g} s after touchdown",
                       f"record too short: need >= {MIN_AFTER_S} s after touchdown and >= "
                       f"{MIN_SAMPLES} samples")
        self.touchdown_time_s, self.onset_channel = t0, onset
        if self.release_time_s is not None:
            self._check_free_fall()
        pre = t < t0 - 0.5 * dt
        if self.release_time_s is not None:  # before release the rig holds the vehicle
            pre &= t > self.release_time_s + 0.5 * dt
        n_pre = int(np.sum(pre))
        acc = "body_accel_mps2"
        if n_pre < MIN_PRE_SAMPLES and acc in self.channels and self.body_accel_kind is None:
            raise _err("body_accel_kind", None, f"missing: the record has {n_pre} samples of "
                       f"free fall before touchdown (< {MIN_PRE_SAMPLES}), too few to tell the "
                       "body acceleration's zero; say what it measures: 'kinematic' (-g in free "
                       "fall) or 'specific_force' (0 in free fall)")
        self.offset_source = (
            "pre-touchdown mean" if n_pre >= MIN_PRE_SAMPLES else
            f"none: {n_pre} samples before touchdown (< {MIN_PRE_SAMPLES}), the sensors' zero "
            "is kept")
        g = float(self.vehicle.g)
        self.offset_samples = n_pre if n_pre >= MIN_PRE_SAMPLES else 0
        for col, vals in self.channels.items():
            free_fall = CHANNELS[base_channel(col)][2]
            free_fall = -g if free_fall is None else free_fall
            seg = vals[pre]
            self.offsets[col] = (float(np.mean(seg)) - free_fall if n_pre >= MIN_PRE_SAMPLES
                                 else 0.0)
            span = float(np.max(vals) - np.min(vals))
            if not span > 0.0:  # its residuals would be weighted by 1 / noise = 1 / 0
                raise _err(f"{self.source}: {col}", f"{float(vals[0]):.6g} throughout",
                           "is constant over the whole record: it carries no information "
                           "(leave the column out)")
            if seg.size >= MIN_NOISE_SAMPLES:
                sig_c, src = float(np.std(seg, ddof=1)), "pre-touchdown segment std"
            else:
                sig_c, src = _highpass_noise(vals), "high-pass (2nd difference MAD)"
            floor = NOISE_FLOOR_REL * span
            if sig_c < floor:
                sig_c, src = floor, f"floor ({NOISE_FLOOR_REL:g} of the channel's range)"
            self.noise_std[col], self.noise_source[col] = sig_c, src
        self._check_plausible()

    def _check_plausible(self) -> None:
        """Refuse, by name, what no drop test of this vehicle can record and a wrong unit or
        sign gives: a stroke beyond the strut's length (mm under an _m header) or running
        negative through the impact (compression is positive); a force that after touchdown
        stays under a tenth of the leg's share of the weight (kN under an _N header, a flipped
        sign); a body acceleration whose swing through the impact is under ``ACCEL_SWING_MIN``
        of what the force channels imply for the leg's mass (g under an _mps2 header: about a
        tenth); a force whose peak exceeds ``PLAUSIBLE_FACTOR`` times what the vehicle can put
        on a leg in this drop (N under a kN header), and a stroke read from a mm column whose
        peak is under 1 / ``PLAUSIBLE_FACTOR`` of what the drop's energy needs (m under a mm
        header)
        (``impact_bounds``); and a given touchdown time after the impact has begun. The forces
        are checked first, and the acceleration last, against the forces. (A body
        acceleration's free-fall level is not checked: the offset makes a specific force
        kinematic.)"""
        t, t0, v = self.time_s, self.touchdown_time_s, self.vehicle
        after = t >= t0
        if self.touchdown_given_s is not None and "normal_force_N" in self.channels:
            f = self.channels["normal_force_N"]  # raw: the offsets assume the touchdown
            f = f - _start_level(f)
            early = f[t < t0 - 0.5 / self.sample_rate_Hz]
            peak = float(np.max(f))
            if early.size and float(np.max(early)) > 0.25 * peak:
                i = int(np.argmax(early > 0.25 * peak))
                raise _err("touchdown_time_s", t0, f"comes after the impact has begun: the "
                           f"normal force is up {early[i]:.4g} N ({early[i] / peak:.0%} of "
                           f"its rise) at {t[i]:.6g} s; give the time the foot meets the "
                           "ground, or leave it out to detect it")
        g = float(v.g)
        share = float(v.m_quarter + v.m_foot) * g  # N, one leg's weight at rest
        length = float(np.min(np.asarray(v.leg.L_h0)))
        corrected = self.corrected
        forces = [c for c in corrected if base_channel(c) in ("normal_force_N", "buffer_force_N")]
        strokes = [c for c in corrected if base_channel(c) == "stroke_m"]
        peaks = {}
        bounds = self.impact_bounds()
        for col in forces:  # first: the stroke's rule reads the forces' peaks
            peak = float(np.max(corrected[col][after]))
            if peak < 0.1 * share:
                raise _err(f"{self.source}: {col}", f"peak {peak:.4g} N", "stays under a "
                           f"tenth of the {share:.4g} N the leg carries at rest: a force "
                           f"in kN (a {col.replace('_N', '_kN')} column is converted), or "
                           "its sign flipped (compression positive)?")
            if peak > PLAUSIBLE_FACTOR * bounds["force_max_N"]:
                name, factor, unit = self._as_written(col)
                raise _err(f"{self.source}: {name}", f"peak {peak / factor:.4g} {unit}",
                           f"exceeds {PLAUSIBLE_FACTOR:g} x the "
                           f"{bounds['force_max_N'] / factor:.4g} {unit} this vehicle can put "
                           f"on a leg in this drop (its strongest crush force with the "
                           f"damping at the {self.touchdown_speed_mps:.3g} m/s touchdown, the "
                           "stop, the foot's impact): "
                           + ("forces in N under a kN header?" if unit == "kN" else
                              "forces in mN under an _N header, or a gain error of the load "
                              "cell?"))
            peaks[base_channel(col)] = max(peaks.get(base_channel(col), 0.0), peak)
        bounds = self.impact_bounds(peaks)
        for col in strokes:
            vals, noise = corrected[col], self.noise_std[col]
            top = float(np.max(np.abs(vals)))
            if top > length:
                raise _err(f"{self.source}: {col}", f"{top:.4g} m", "exceeds the strut's "
                           f"length ({length:.4g} m, leg.L_h0_m): a stroke in mm? (a "
                           f"{col.replace('_m', '_mm')} column is converted)")
            crush = float(np.max(np.asarray(v.honeycomb.x_L4)))
            if top > STROKE_PAST_CRUSH * crush:  # the bottoming stop ends the stroke at x_L4
                name, factor, unit = self._as_written(col)
                raise _err(f"{self.source}: {name}", f"{top / factor:.4g} {unit}",
                           f"exceeds {STROKE_PAST_CRUSH:g} x the honeycomb's crush length "
                           f"({crush * 1e3:.4g} mm, honeycomb.x_L4_mm), where the bottoming "
                           "stop ends the stroke: "
                           + ("a stroke in tenths of a mm or in um under a stroke_mm header"
                              if unit == "mm" else
                              "a stroke in inches or cm under a stroke_m header")
                           + ", or the vehicle's x_L4 not the gear's?")
            lo, hi = float(np.min(vals[after])), float(np.max(vals[after]))
            if -lo > 4.0 * max(hi, 0.0) and -lo > 20.0 * noise:
                raise _err(f"{self.source}: {col}", f"{lo:.4g} m", "runs negative after "
                           f"touchdown (up to {hi:.3g} m the other way): a stroke is "
                           "positive in compression; flip its sign")
            need = bounds["stroke_min_m"]
            name, factor, unit = self._as_written(col)
            # the ground's share of the energy is bounded with the vehicle's ground stiffness,
            # which a fit may find far softer: judged only where a mm column was converted,
            # whose m values (a thousand times too small) it is for
            if unit == "mm" and hi < need / PLAUSIBLE_FACTOR:
                by = {k: peaks[k] for k in ("normal_force_N", "buffer_force_N") if k in peaks}
                raise _err(f"{self.source}: {name}", f"peak {hi / factor:.4g} {unit}",
                           f"is under 1/{PLAUSIBLE_FACTOR:g} of the {need / factor:.4g} {unit} "
                           f"this drop needs: the leg's body share must absorb "
                           f"{bounds['energy_J']:.4g} J ({float(v.m_quarter):.4g} kg at "
                           f"{self.touchdown_speed_mps:.3g} m/s), the ground at most "
                           f"{bounds['ground_energy_J']:.4g} J of it, the strut the rest at "
                           "most at "
                           + (f"the record's peak buffer force ({by['buffer_force_N']:.4g} N)"
                              if "buffer_force_N" in by else
                              f"the vehicle's strongest strut force "
                              f"({bounds['strut_force_N']:.4g} N)")
                           + ": a stroke in m under a stroke_mm header?")
        self._check_accel_scale(after)

    def _as_written(self, col: str) -> tuple[str, float, str]:
        """A channel as the record wrote it: (its column, the factor its values were converted
        to SI with, its unit): ``('normal_force_kN', 1000.0, 'kN')`` for a converted kN column,
        ``(col, 1.0, the SI unit)`` otherwise."""
        for text in self.unit_conversions.values():
            given, arrow, rest = text.partition(" -> ")
            si, _, factor = rest.partition(" (x ")
            if arrow and si == col:
                return given, float(factor.rstrip(")")), given.rpartition("_")[2]
        return col, 1.0, CHANNELS[base_channel(col)][0]

    def impact_bounds(self, peaks: dict | None = None) -> dict:
        """What the vehicle can do to one leg on this drop (SI), the scales of the plausibility
        rules (``PLAUSIBLE_FACTOR`` beyond them is refused). ``peaks``: the record's largest
        ``normal_force_N`` and ``buffer_force_N`` over its legs, where it has them.

        ``strut_force_N``: the strongest strut force before the stop, the honeycomb's strongest
        crush force (plateaus and peaks) times the structural damping's (1 + D_b v_td) at the
        touchdown speed. ``force_max_N``: the largest force a channel can carry, that strut
        force, plus the stop's sqrt(2 E k_bottom) (times the damping's factor) for the energy
        E the honeycomb's plateaus cannot absorb before it (the leg's and the foot's, at
        touchdown and falling the stop's stroke x_L4 too), plus the foot's own impact on the
        ground, v_td sqrt(k m_foot). ``energy_J``: the body share's kinetic energy at
        touchdown, m_quarter v_td^2 / 2, the least the leg must absorb. ``ground_energy_J``:
        the most the ground absorbs, F_N^2 / k (a pit of at most F_N / k under a force of at
        most F_N, the record's peak normal force, or the strut force without one).
        ``stroke_min_m``: the least stroke that absorbs the rest at a strut force of at most
        F_B (the record's peak buffer force, or the strut force without one): (energy_J -
        ground_energy_J) / F_B, 0 where the ground can take it all."""
        v, hc = self.vehicle, self.vehicle.honeycomb
        peaks = peaks or {}
        f = lambda x: float(np.max(np.asarray(x)))  # noqa: E731
        vt = float(self.touchdown_speed_mps)
        peak1 = max(f(hc.peak_ratio1) if hc.peak_ratio1 is not None else 1.0,
                    1.0 + f(hc.excess1) if hc.excess1 is not None and np.size(hc.excess1)
                    else 1.0)
        peak2 = f(hc.peak_ratio2) if hc.peak_ratio2 is not None else 1.0
        damping = 1.0 + f(v.leg.D_b) * vt
        strut = max(f(hc.F1) * peak1, f(hc.F2) * peak2) * damping
        x_l1 = f(hc.F1) / f(hc.k_b1)
        x_l3 = f(hc.x_L2) + (f(hc.F2) - f(hc.F1)) / f(hc.k_b3)
        capacity = f(hc.F1) * (f(hc.x_L2) - x_l1) + f(hc.F2) * max(f(hc.x_L4) - x_l3, 0.0)
        total = float(v.m_quarter + v.m_foot) * (0.5 * vt * vt + float(v.g) * f(hc.x_L4))
        stop = math.sqrt(2.0 * max(total - capacity, 0.0) * f(hc.k_bottom)) * damping
        k_ground = f(v.ground.k)
        force_max = strut + stop + vt * math.sqrt(k_ground * float(v.m_foot))
        energy = 0.5 * float(v.m_quarter) * vt * vt
        f_n = peaks.get("normal_force_N", strut)
        ground = f_n * f_n / k_ground
        stroke_min = max(energy - ground, 0.0) / peaks.get("buffer_force_N", strut)
        return dict(strut_force_N=strut, force_max_N=force_max, energy_J=energy,
                    ground_energy_J=ground, stroke_min_m=stroke_min)

    def _check_accel_scale(self, after) -> None:
        """The body acceleration's swing after touchdown (peak to peak, of a 3-sample running
        median, so that one glitch does not set it) against each force channel's divided by
        the leg's mass (the body's share): 0.93 to 1.0 for the ground's normal force and 0.52
        to 0.67 for the strut's buffer force on the bundled records and rig drops of 0.01 to
        1 m, a tenth of that in g. Refused by name below ``ACCEL_SWING_MIN`` of the smaller
        implied swing, above ``ACCEL_SWING_MAX`` times the larger for a column converted from
        g (m/s^2 under a g header) and ``PLAUSIBLE_FACTOR`` times it otherwise (a unit a
        thousand times off); and where it runs against every force channel
        (correlation below -``ACCEL_ANTICORRELATION``: its sign flipped; the swing cannot
        see a sign); a record without a force channel is not checked."""
        m = float(self.vehicle.m_quarter)
        corrected = self.corrected

        def swing(col):
            x = corrected[col][after]
            if x.size >= 3:
                x = np.median(np.stack([x[:-2], x[1:-1], x[2:]]), axis=0)
            return float(np.ptp(x))

        acc = [c for c in corrected if base_channel(c) == "body_accel_mps2"]
        forces = [c for c in corrected if base_channel(c) in ("normal_force_N", "buffer_force_N")]
        if not (acc and forces):
            return
        # the least a force channel implies bounds the swing from below, the most from above:
        # a leg that barely loaded tightens neither
        implied = min(swing(c) / m for c in forces)
        most = max(swing(c) / m for c in forces)
        for col in acc:
            a = swing(col)
            if a < ACCEL_SWING_MIN * implied:
                raise _err(f"{self.source}: {col}", f"swing {a:.4g} m/s^2", "must be at least "
                           f"{ACCEL_SWING_MIN:g} of the swing the force channels imply for the "
                           f"leg's {m:.4g} kg ({implied:.4g} m/s^2; records in m/s^2 give 0.5 "
                           f"to 1), and is {a / implied:.2g} of it: an acceleration in g? (a "
                           "body_accel_g column is converted)")
            name, _, unit = self._as_written(col)
            if unit == "g" and a > ACCEL_SWING_MAX * most:
                raise _err(f"{self.source}: {name}", f"swing {a:.4g} m/s^2", "must be at most "
                           f"{ACCEL_SWING_MAX:g} x the swing the force channels imply for the "
                           f"leg's {m:.4g} kg ({most:.4g} m/s^2; records give 0.5 to 1), and "
                           f"is {a / most:.3g} x it after the conversion from g "
                           f"(x {STANDARD_GRAVITY:g}): values in m/s^2 under a g header?")
            if a > PLAUSIBLE_FACTOR * most:
                raise _err(f"{self.source}: {col}", f"swing {a:.4g} m/s^2", "must be at most "
                           f"{PLAUSIBLE_FACTOR:g} x the swing the force channels imply for the "
                           f"leg's {m:.4g} kg ({most:.4g} m/s^2; records in m/s^2 give 0.5 "
                           f"to 1), and is {a / most:.3g} x it: an acceleration in mm/s^2 "
                           "under an _mps2 header, or a gain error of the accelerometer?")
            x = corrected[col][after]
            corr = [float(np.corrcoef(x, corrected[c][after])[0, 1]) for c in forces
                    if np.ptp(corrected[c][after]) > 0.0 and np.ptp(x) > 0.0]
            if corr and max(corr) < -ACCEL_ANTICORRELATION:
                raise _err(f"{self.source}: {name}", f"correlation {max(corr):.2f}",
                           "with the force channels through the impact: the body acceleration "
                           "runs against the forces that cause it (records give 0.95 to "
                           "0.995): its sign flipped? (upward positive)")

    def _check_free_fall(self) -> None:
        """The drop height the free fall from release to touchdown implies against the
        metadata's: refused by name when they disagree (``FREE_FALL_REL``, ``FREE_FALL_ABS_M``).
        """
        g = float(self.vehicle.g)
        t_ff = self.touchdown_time_s - self.release_time_s
        h, v0 = self.drop_height_m, self.sink_speed_mps
        if t_ff <= 0.0:
            raise _err("release_time_s", self.release_time_s, f"must precede the touchdown "
                       f"({self.touchdown_time_s:.6g} s on the record's axis)")
        h_ff = v0 * t_ff + 0.5 * g * t_ff * t_ff
        t_h = (math.sqrt(v0 * v0 + 2.0 * g * h) - v0) / g
        tol = max(FREE_FALL_REL * h, FREE_FALL_ABS_M)
        self.free_fall = dict(release_time_s=self.release_time_s,
                              touchdown_time_s=self.touchdown_time_s, free_fall_s=t_ff,
                              free_fall_of_drop_height_s=t_h, implied_drop_height_m=h_ff,
                              tolerance_m=tol)
        if abs(h_ff - h) > tol:
            raise _err("drop_height_m", h, f"contradicts the record's free fall: release at "
                       f"{self.release_time_s:.6g} s and touchdown at "
                       f"{self.touchdown_time_s:.6g} s ({t_ff * 1e3:.1f} ms of free fall"
                       f"{f' from {v0:g} m/s' if v0 else ''}) mean a drop of {h_ff:.4g} m, "
                       f"while {h:g} m falls in {t_h * 1e3:.1f} ms; they must agree within "
                       f"{FREE_FALL_REL:.0%} or {FREE_FALL_ABS_M * 1e3:g} mm")

    @property
    def corrected(self) -> dict:
        """Channels with the offsets removed."""
        return {c: v - self.offsets[c] for c, v in self.channels.items()}

    def gain_reference(self, col: str) -> float:
        """The value of the corrected column ``col`` that an error in its gain leaves as it
        is [its unit]: a gain scales the reading's distance from it. The free-fall level (-g
        for the body acceleration, 0 for the others) where the offset pins the free fall to
        it or the column is a specific-force accelerometer's (0 in free fall); else 0, the
        sensor's own zero."""
        level = CHANNELS[base_channel(col)][2]
        level = -float(self.vehicle.g) if level is None else level
        pinned = self.offset_samples > 0 or (base_channel(col) == "body_accel_mps2"
                                             and self.body_accel_kind == "specific_force")
        return level if pinned else 0.0

    @property
    def duration_after_touchdown_s(self) -> float:
        return float(self.time_s[-1] - self.touchdown_time_s)

    def filter_coefficients(self, col: str) -> np.ndarray:
        """The J211 pass coefficients of column ``col`` (``_filter.IDENTITY``: no filter)."""
        from ._filter import IDENTITY, cfc_coefficients

        cfc = self.filters.get(col)
        return IDENTITY.copy() if cfc is None else cfc_coefficients(cfc, self.sample_rate_Hz)

    def summary(self) -> dict:
        """Metadata and preprocessing, JSON-ready (units in the keys)."""
        return dict(
            name=self.name, source=self.source, synthetic=self.synthetic,
            drop_height_m=self.drop_height_m, sink_speed_mps=self.sink_speed_mps,
            touchdown_speed_mps=self.touchdown_speed_mps, sample_rate_Hz=self.sample_rate_Hz,
            n_samples=int(self.time_s.size), sensor_leg=self.sensor_leg,
            channels=list(self.channels),
            legs={c: leg_of(c, self.sensor_leg) for c in self.channels},
            touchdown_time_s=self.touchdown_time_s,
            touchdown_detected_from=self.onset_channel,
            release_time_s=self.release_time_s, free_fall_check=self.free_fall or None,
            body_accel_kind=self.body_accel_kind,
            offsets={f"{c}": v for c, v in self.offsets.items()},
            offset_source=self.offset_source,
            noise_std={f"{c}": v for c, v in self.noise_std.items()},
            noise_source=dict(self.noise_source),
            unit_conversions=dict(self.unit_conversions),
            filter_cfc=dict(self.filters) or None,
            filter_data_prefiltered=self.filter_data_prefiltered,
            gain_uncertainty_rel=dict(self.gain_uncertainty_rel) or None,
        )


def _per_column(key: str, spec, chans: dict) -> dict:
    """{column: value} from a metadata key ``key`` given as one value for every column or as
    a table by column (``spec``; None: {}), each table entry naming a column of ``chans``."""
    if spec is None:
        return {}
    if not isinstance(spec, dict):
        return {c: spec for c in chans}
    for col, value in spec.items():
        if col not in chans:
            raise _err(f"{key}.{col}", value, "names no column of the record (after unit "
                       "conversion); columns: " + ", ".join(chans))
    return dict(spec)


def _filters(spec, chans: dict, rate: float) -> dict:
    """{column: CFC class} from the metadata's ``filter_cfc`` (one class or a table)."""
    from ._filter import CFC_CLASSES, min_rate_Hz

    out = _per_column("filter_cfc", spec, chans)
    for col, cfc in out.items():
        if isinstance(cfc, bool) or cfc not in CFC_CLASSES:
            raise _err("filter_cfc", cfc, "must be one of the SAE J211 channel frequency "
                       "classes " + ", ".join(str(c) for c in CFC_CLASSES))
        if rate <= min_rate_Hz(cfc):
            raise _err("filter_cfc", cfc, f"needs a sample rate above {min_rate_Hz(cfc):g} Hz "
                       f"(2 x 2.0775 x CFC, the J211 filter design's limit); the record has "
                       f"{rate:g} Hz")
    return {c: int(v) for c, v in out.items()}



def _gain_uncertainty(spec, chans: dict) -> dict:
    """{column: relative standard uncertainty of its gain} from the metadata's
    ``gain_uncertainty_rel`` (one number for every column or a table); a zero is left out."""
    out = _per_column("gain_uncertainty_rel", spec, chans)
    for col, rel in out.items():
        if isinstance(rel, bool) or not isinstance(rel, (int, float)) or not (
                0.0 <= rel <= GAIN_UNCERTAINTY_MAX):
            raise _err("gain_uncertainty_rel" + (f".{col}" if isinstance(spec, dict) else ""),
                       rel, f"must be a number in [0, {GAIN_UNCERTAINTY_MAX:g}] (relative: 0.005 "
                       "for 0.5 %)")
    return {c: float(v) for c, v in out.items() if v > 0.0}


def _stroke_onset(y: np.ndarray, i_c: int, base: float, sig: float) -> tuple[int, float]:
    """Where a stroke leaves its level before the impact: ``(index, level)``, from ``i_c``,
    its first sample past the onset threshold. A force or an acceleration jumps at
    touchdown, but the stroke grows from rest (the strut compresses only as the foot's force
    builds), so its crossing of 5 % of the rise comes milliseconds late (5.6 ms on the
    bundled 0.2 m drop). The level is the median just before the rise could have begun
    (STROKE_ONSET_REACH times the straight-line time back from the crossing: the rise is
    convex), not the record's start, and the walk back along the samples more than
    STROKE_ONSET_SIGMAS noise sigmas from it stops there: a sensor's drift before the impact
    is no onset."""
    k = min(i_c + 2, len(y) - 1)
    rate = abs(y[k] - y[i_c - 2]) / (k - i_c + 2)  # per sample, at the crossing
    reach = int(min(i_c - MIN_PRE_SAMPLES, max(
        2, math.ceil(STROKE_ONSET_REACH * abs(y[i_c] - base) / rate) if rate > 0 else 2)))
    start = i_c - reach
    level = float(np.median(y[max(start - MIN_PRE_SAMPLES, 0):start + 1]))
    while i_c > start and abs(y[i_c - 1] - level) > STROKE_ONSET_SIGMAS * sig:
        i_c -= 1
    return i_c, level


def _highpass_noise(y: np.ndarray) -> float:
    """Robust white-noise std from second differences: MAD / 0.6745 / sqrt(6)."""
    d2 = np.diff(y, 2)
    if d2.size == 0:
        return 0.0
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return mad / 0.6745 / math.sqrt(6.0)


def _as_trace(name, vals) -> np.ndarray:
    try:
        arr = np.asarray(vals, dtype=np.float64)
    except (TypeError, ValueError):
        raise _err(name, "<non-numeric>", "must hold numbers only") from None
    if arr.ndim != 1:
        raise _err(name, f"shape {arr.shape}", "must be one trace (1-D)")
    bad = ~np.isfinite(arr)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise _err(name, float(arr[i]), f"must be finite: sample {i} (data row {i + 2}) is "
                   f"{arr[i]}; remove or repair NaN/inf samples")
    return arr


def _start_level(y: np.ndarray) -> float:
    """A channel's level at the record's start: the median of its first few samples (what
    touchdown detection rises from)."""
    return float(np.median(y[:max(MIN_PRE_SAMPLES // 2, 3)]))


def _check_column_name(col: str, where: str = "") -> None:
    """Refuse a column name that is no channel (``where``: the file, named in the message)."""
    field_ = f"{where}: column {col!r}" if where else f"column {col!r}"
    m = LEG_COLUMN.match(col)
    if m:  # a leg's channel: the channel's rules, and the body's acceleration has no leg
        base = m.group(2)
        if base.startswith("body_accel") or base.startswith("time"):
            raise _err(field_, col, f"{base.rpartition('_')[0] or base} takes no "
                       "leg prefix (it is the body's); legs carry normal_force, buffer_force "
                       "and stroke")
        _check_column_name(base, where)
        return
    if col in CHANNELS or col == TIME or col in CONVERSIONS:
        return
    base, _, unit = col.rpartition("_")
    for name, want in _UNIT_SUFFIX.items():
        if col == name or base == name:
            right = f"{name}_{want}"
            got = "no unit suffix" if col == name else f"unit '{unit}'"
            raise _err(field_, col, f"unit suffix missing or wrong ({got}): the "
                       f"{name} channel must be in {_UNIT_WORDS[want]}, named {right!r} "
                       f"(or one of the converted units: "
                       f"{', '.join(c for c in CONVERSIONS if c.startswith(name))})")
    raise _err(field_, col, "unknown column; known: " + ", ".join(
        [TIME, *CHANNELS]) + " (per leg: leg<i>_normal_force_N, leg<i>_buffer_force_N, "
        "leg<i>_stroke_m)")


def _check_time(t: np.ndarray, rate) -> None:
    if t.size < 2:
        raise _err("time_s", f"{t.size} samples", f"record too short: need >= {MIN_SAMPLES}")
    dt = np.diff(t)
    if np.any(dt <= 0):
        i = int(np.argmax(dt <= 0))
        raise _err("time_s", float(t[i + 1]), f"must increase strictly: sample {i + 1} (data "
                   f"row {i + 3}) is not after the one before ({t[i]})")
    if t.size < MIN_SAMPLES:
        raise _err("time_s", f"{t.size} samples", f"record too short: need >= {MIN_SAMPLES}")
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not (
            math.isfinite(rate) and rate > 0):
        raise _err("sample_rate_Hz", rate, "must be a finite number > 0 Hz")
    median = float(np.median(dt))
    if abs(median * rate - 1.0) > 0.01:
        raise _err("sample_rate_Hz", rate, f"does not match the time column: its median "
                   f"interval {median:.6g} s means {1.0 / median:.6g} Hz (tolerance 1 %)")
    if rate < MIN_SAMPLE_RATE_HZ:
        raise _err(TIME, f"{median:.6g} s between samples", f"means {1.0 / median:.6g} Hz "
                   f"(sample_rate_Hz = {rate!r}); a drop record needs >= "
                   f"{MIN_SAMPLE_RATE_HZ:g} Hz, its impact lasting tens of ms: times in ms "
                   f"under a {TIME} header? (a time_ms column is converted)")
    _check_uniform(t, float(rate))
    span = float(t[-1] - t[0])
    if span > MAX_RECORD_S:
        raise _err(TIME, f"{span:.6g} s from first to last sample", f"must be <= "
                   f"{MAX_RECORD_S:g} s: a drop record spans seconds (the fall from the "
                   "highest drop_height_m, 50 m, takes 3.2 s, and a landing settles within "
                   "one), and fit and predict simulate all of it after touchdown; times in ms "
                   f"under a {TIME} header, or trim the record")


def _check_uniform(t: np.ndarray, rate: float) -> None:
    """Refuse a time column that is not sampled uniformly (``INTERVAL_REL``, ``GRID_REL``),
    naming the time and size of the worst interval, or of the sample furthest off the grid."""
    step = 1.0 / rate
    dt = np.diff(t)
    off = np.abs(dt / step - 1.0)
    i = int(np.argmax(off))
    if off[i] > INTERVAL_REL:
        ratio = float(dt[i] / step)
        gap = ratio > 1.5
        what = (f"a gap: about {round(ratio) - 1} sample(s) missing" if gap else
                "a sample out of step, or a clock that changes its rate")
        raise _err(TIME, f"{dt[i]:.6g} s between samples at {t[i]:.6g} s",
                   f"is {ratio:.3g} x 1/sample_rate_Hz ({step:.6g} s) after sample {i} (data "
                   f"row {i + 2}), {what}; every interval must be within "
                   f"{INTERVAL_REL:.0%} of it: the record must be sampled uniformly (the CFC "
                   "filter, the noise estimate and the error bars count samples); "
                   + ("cut the record at the gap" if gap else "correct the time column"))
    k = np.arange(t.size, dtype=np.float64)
    slope, start = np.polyfit(k, t - t[0], 1)
    dev = (t - t[0] - (start + slope * k)) / slope
    j = int(np.argmax(np.abs(dev)))
    if abs(dev[j]) > GRID_REL:
        half = t.size // 2
        early, late = float(np.median(dt[:half])), float(np.median(dt[half:]))
        raise _err(TIME, f"{t[j]:.6g} s, {dev[j]:+.3g} intervals off the uniform grid",
                   f"every sample must lie within {GRID_REL:g} intervals of the uniform grid "
                   f"fitted through the time column (a uniformly sampled record): its rate "
                   f"changes along the record ({1.0 / early:.6g} Hz in its first half, "
                   f"{1.0 / late:.6g} Hz in its second; sample_rate_Hz = {rate:g})")


def _num(key, val, field, lo_open=False):
    """``val`` of metadata ``key`` inside the scene envelope of ``jaxland``'s scene field
    ``field`` (``SCENE_FIELDS``: its limits and unit)."""
    from jaxland._scene import SCENE_FIELDS

    lo, hi, unit = SCENE_FIELDS[field].lo, SCENE_FIELDS[field].hi, SCENE_FIELDS[field].unit
    if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
        raise _err(key, val, "must be a finite number")
    if val < lo or val > hi or (lo_open and val == lo):
        raise _err(key, val, f"must be in {'(' if lo_open else '['}{lo:g}, {hi:g}] {unit}")
    return float(val)


def _touchdown_speed(h, v0, v_td, g):
    if v_td is not None:
        if h is not None or v0 is not None:
            raise _err("touchdown_speed_mps", v_td, "give either touchdown_speed_mps or "
                       "drop_height_m (with optional sink_speed_mps), not both")
        return _num("touchdown_speed_mps", v_td, "sink_speed", lo_open=True), None, 0.0
    if h is None:
        raise _err("drop_height_m", None, "missing: give drop_height_m (optionally with "
                   "sink_speed_mps) or touchdown_speed_mps")
    h = _num("drop_height_m", h, "drop_height")
    v0 = 0.0 if v0 is None else _num("sink_speed_mps", v0, "sink_speed")
    v = math.sqrt(v0 * v0 + 2.0 * g * h)
    if v <= 0.0:
        raise _err("drop_height_m", h, "with sink_speed_mps = 0 must be > 0 (no impact)")
    return v, h, v0


# ---------------------------------------------------------------------------------- files

def _read_csv(path: Path):
    # refuses missing, folder and non-UTF-8 files; drops a spreadsheet's byte-order mark
    text = jl.read_text(path, "data_file")
    reader = csv.reader(io.StringIO(text, newline=""))
    rows, lines = [], []  # the rows, and each one's line in the file (comments skipped)
    for r in reader:
        if r and not r[0].lstrip().startswith("#"):
            rows.append(r)
            lines.append(reader.line_num)
    if not rows:
        raise _err(str(path), "<empty>", "needs a header row and data")
    header = [h.strip() for h in rows[0]]
    if TIME not in header and "time_ms" not in header:
        near = [h for h in header if h.startswith("time")]
        if near:
            _check_column_name(near[0], path.name)
        raise _err(f"{path.name}: columns", ",".join(header), "missing column time_s (the "
                   "sample times in s)")
    seen = set()
    for h in header:
        if h in seen:
            raise _err(f"{path.name}: column {h!r}", h, "appears twice")
        seen.add(h)
        _check_column_name(h, path.name)
    data = []
    for i, row in zip(lines[1:], rows[1:]):
        if len(row) != len(header):
            raise _err(f"{path.name}: row {i}", len(row), f"must have {len(header)} values "
                       f"(one per column: {','.join(header)}); a value is missing or extra")
        try:
            data.append([float(x) for x in row])
        except ValueError:
            bad = next(x for x in row if not _is_float(x))
            col = header[row.index(bad)]
            raise _err(f"{path.name}: row {i}, {col}", bad, "must be a number") from None
    arr = np.array(data, dtype=np.float64).reshape(-1, len(header))
    bad = ~np.isfinite(arr)
    if np.any(bad):  # named here, by the file's line and the column as written
        i, j = (int(x) for x in np.argwhere(bad)[0])
        raise _err(f"{path.name}: row {lines[i + 1]}, {header[j]}", float(arr[i, j]),
                   "must be finite: remove or repair NaN/inf samples")
    return {h: arr[:, j] for j, h in enumerate(header)}


def _is_float(x):
    try:
        float(x)
        return True
    except ValueError:
        return False


def _meta_paths(path: Path) -> tuple[Path, dict]:
    path = Path(path)
    if path.suffix == ".csv":
        meta_path = path.with_suffix(".toml")
        if not meta_path.exists():
            raise _err("metadata", str(meta_path), f"missing: a drop test needs a metadata "
                       f"TOML beside {path.name} ([drop_test] table)")
    else:
        meta_path = path
    if meta_path.is_dir():
        raise _err("DATA", str(meta_path), "is a folder: give a drop test's metadata TOML (or "
                   "its CSV)")
    # jaxland's TOML reader: its refusals (missing, unreadable, not UTF-8, not TOML)
    from jaxland._toml import read_toml

    return meta_path, read_toml(meta_path, "metadata")


# keys a vehicle given in place of a drop's vehicle_config may change: the model's parameters
# that jaxland fit calibrates (calibration._parameters.PARAMS) and the crush peak's table
_TABLE_KEYS = ("honeycomb.excess1", "honeycomb.excess_length1_mm")


def _flat_vehicle(vehicle: jl.Vehicle) -> dict:
    """``{'body.m_body_kg': 1120.0, ...}``: every key of the vehicle's TOML."""
    out = {}

    def walk(prefix, table):
        for k, val in table.items():
            if isinstance(val, dict):
                walk(f"{prefix}{k}.", val)
            else:
                out[prefix + k] = val
    walk("", tomllib.loads(jl.vehicle_to_toml(vehicle)))
    return out


def article_fingerprint(vehicle: jl.Vehicle) -> str:
    """SHA-256 (16 hex digits) of every key of the vehicle's TOML outside the parameters
    jaxland fit calibrates (``PARAMS``: fitted, held or off, each compared by name): the test
    article, and a crush peak's table, as written. A fitted file records it, so that predict
    sees an edit of a mass or a length too."""
    import hashlib
    import json

    from ._parameters import PARAMS

    flat = _flat_vehicle(vehicle)
    skip = {p[2] for p in PARAMS.values()}
    if not flat.get("honeycomb.excess1"):  # no table: its length acts on nothing
        skip.add("honeycomb.excess_length1_mm")
    rest = {k: v for k, v in sorted(flat.items()) if k not in skip}
    return hashlib.sha256(json.dumps(rest, sort_keys=True).encode()).hexdigest()[:16]


def article_differences(declared: jl.Vehicle, given: jl.Vehicle) -> list[tuple]:
    """The keys outside the calibrated parameters (the test article: masses, inertias, gravity,
    legs and their geometry, the honeycomb's lengths and stops) in which ``given`` differs from
    ``declared``: ``[(key, declared value, given value)]``."""
    from ._parameters import PARAMS

    free = {p[2] for p in PARAMS.values()} | set(_TABLE_KEYS)
    a, b = _flat_vehicle(declared), _flat_vehicle(given)
    out = []
    for key in a:
        if key in free or key not in b:
            continue
        x, y = a[key], b[key]
        same = (math.isclose(x, y, rel_tol=1e-9, abs_tol=0.0)
                if isinstance(x, (int, float)) and isinstance(y, (int, float))
                and not isinstance(x, bool) else x == y)
        if not same:
            out.append((key, x, y))
    return out


def check_same_article(declared: jl.Vehicle, given: jl.Vehicle, where: str,
                       given_name: str = "vehicle") -> None:
    """Refuse ``given`` (named ``given_name``) in place of a drop's ``vehicle_config``
    (``declared``, named ``where``) where it describes another test article
    (``article_differences``), naming the first key that differs and both values."""
    diff = article_differences(declared, given)
    if diff:
        key, was, now = diff[0]
        more = f" (and {len(diff) - 1} more key(s))" if len(diff) > 1 else ""
        raise _err(f"{where}: {key}", was,
                   f"differs from {given_name}'s {now!r}{more}: the drop was made with the "
                   f"article its vehicle_config describes, and {given_name} may change only "
                   f"the parameters jaxland fit calibrates; give a {given_name.split()[0]} of "
                   "that article, or correct the drop's vehicle_config")


def load_drop_test(path, *, vehicle: jl.Vehicle | None = None,
                   vehicle_name: str = "vehicle") -> DropTest:
    """Load one drop test from its metadata TOML (or its CSV, with the TOML beside it of the
    same name), validate everything and preprocess (touchdown, offsets, noise).

    ``vehicle`` overrides the metadata's ``vehicle_config`` in the parameters ``jaxland fit``
    calibrates; where the metadata names a ``vehicle_config``, ``vehicle`` must describe that
    test article in every other key (``check_same_article``), or the drop is refused naming
    the ``vehicle_config``, the key, both values and ``vehicle_name`` (the CLI's ``--config
    PATH``). Raises ``jaxland.ConfigError`` naming the field (file, column or key), the value
    and the rule.
    """
    meta_path, meta = _meta_paths(Path(path))
    unknown = set(meta) - {"drop_test", *_OPTIONAL_TABLES}
    if "drop_test" not in meta or unknown:
        raise _err(f"{meta_path.name}", sorted(unknown) or "<no [drop_test]>",
                   "needs a [drop_test] table (and optionally [synthetic_rig]); nothing else")
    table = meta["drop_test"]
    for key in table:
        if key not in META_KEYS:
            raise _err(f"{meta_path.name}: drop_test.{key}", table[key],
                       "unknown key; known: " + ", ".join(META_KEYS))
    if "sample_rate_Hz" not in table:
        raise _err(f"{meta_path.name}: drop_test.sample_rate_Hz", None, "missing: the sample "
                   "rate of the traces [Hz]")
    data_file = table.get("data_file", meta_path.with_suffix(".csv").name)
    if not isinstance(data_file, str):
        raise _err("drop_test.data_file", data_file, "must be a file name (string)")
    csv_path = (meta_path.parent / data_file)
    cfg = table.get("vehicle_config")
    declared = None
    if cfg is not None and not isinstance(cfg, str):
        raise _err("drop_test.vehicle_config", cfg, "must be a file name (string)")
    if cfg is not None:
        try:
            declared = jl.load_vehicle(meta_path.parent / cfg)
        except jl.ConfigError as err:  # name the file the value is in
            raise _err(f"{meta_path.name}: drop_test.vehicle_config {cfg}: {err.field}",
                       err.value, err.rule) from None
    if vehicle is None:
        vehicle = jl.paper_vehicle() if declared is None else declared
    elif declared is not None:
        check_same_article(declared, vehicle, f"{meta_path.name}: drop_test.vehicle_config "
                           f"{cfg}", vehicle_name)
    cols = _read_csv(csv_path)
    time_conv = {}
    if "time_ms" in cols:
        if TIME in cols:
            raise _err(f"{csv_path.name}: column 'time_ms'", "time_ms",
                       "given twice: as time_ms and as time_s")
        cols[TIME] = cols.pop("time_ms") * CONVERSIONS["time_ms"][1]
        time_conv = {"time_ms": f"time_ms -> {TIME} (x {CONVERSIONS['time_ms'][1]:g})"}
    time_s = cols.pop(TIME)
    where = f"{csv_path.name}"
    try:
        drop = DropTest.from_arrays(
            time_s, cols, sample_rate_Hz=table["sample_rate_Hz"],
            drop_height_m=table.get("drop_height_m"), sink_speed_mps=table.get("sink_speed_mps"),
            touchdown_speed_mps=table.get("touchdown_speed_mps"),
            sensor_leg=table.get("sensor_leg", 0), vehicle=vehicle, vehicle_config=cfg,
            name=meta_path.stem, synthetic=table.get("synthetic", False),
            description=table.get("description", ""), source=where,
            touchdown_time_s=table.get("touchdown_time_s"),
            release_time_s=table.get("release_time_s"),
            body_accel_kind=table.get("body_accel_kind"), filter_cfc=table.get("filter_cfc"),
            filter_data_prefiltered=table.get("filter_data_prefiltered", False),
            gain_uncertainty_rel=table.get("gain_uncertainty_rel"))
        drop.unit_conversions = {**time_conv, **drop.unit_conversions}
        drop.files = (meta_path, csv_path) + ((meta_path.parent / cfg,) if cfg else ())
        return drop
    except jl.ConfigError as err:
        if err.field.startswith(where):
            raise
        if err.field.split(".")[0] in META_KEYS:  # a metadata value (alone or with the time)
            raise _err(f"{meta_path.name}: drop_test.{err.field}", err.value,
                       err.rule) from None
        raise _err(f"{where}: {err.field}", err.value, err.rule) from None


def check_drop_names(drops, paths) -> None:
    """Refuse two drop tests of one name (``DropTest.name``, the metadata file's stem): each
    drop's outputs are named after it, and in a fit each drop counts once, so a drop given
    twice (as its TOML and its CSV too) or two drops of one name would silently overwrite or
    double-count."""
    seen = {}
    for d, p in zip(drops, paths):
        if d.name in seen:
            raise _err("DATA", f"{seen[d.name]} and {p}", f"are both drop test {d.name!r}: a "
                       "drop is given once, and drops need different names (their outputs are "
                       "named after them)")
        seen[d.name] = p


def load_drop_tests(paths, *, vehicle: jl.Vehicle | None = None,
                    vehicle_name: str = "vehicle") -> list[DropTest]:
    """``load_drop_test`` for each path; the drops must share one vehicle configuration and
    have different names (``check_drop_names``)."""
    drops = [load_drop_test(p, vehicle=vehicle, vehicle_name=vehicle_name) for p in paths]
    if not drops:
        raise _err("DATA", "<none>", "give at least one drop test")
    check_drop_names(drops, paths)
    first = jl.vehicle_to_toml(drops[0].vehicle)
    for d in drops[1:]:
        if jl.vehicle_to_toml(d.vehicle) != first:
            raise _err(f"{d.source}: vehicle_config", d.vehicle_config,
                       f"differs from {drops[0].source}'s; drops fitted together must share "
                       "one vehicle (or pass one with --config)")
    return drops
