"""A virtual drop-test rig: synthetic drop tests with known truth, since no measured data is
public.

The rig drops a vehicle whose parameters are the **truth** (the paper vehicle perturbed by
``TRUTH_SCALE``, below) with jaxland's quarter model, from release, at dt = 1e-5 s, and records
what a real rig records, with what a real rig adds:

* **sampling**: 5 kHz, a record of ``duration_s`` (1.2 s) that starts ``pre_trigger_s``
  (50 ms) before touchdown; the record's time axis starts at 0, so touchdown is not at a known
  time and has to be found;
* **sensor noise**: white Gaussian, ``NOISE`` per channel;
* **a stroke offset**: the stroke sensor is not zeroed (``STROKE_OFFSET_M``);
* **a crush peak**, which the model does not have: honeycomb needs a higher stress to start
  crushing than to keep crushing. Both force channels are multiplied by
  ``1 + CRUSH_PEAK * s(p / p0)`` with ``s(u) = u exp(1 - u)`` (peak 1 at u = 1), p the primary
  honeycomb's crushed length and p0 = ``CRUSH_PEAK_LENGTH_M`` (0.4 mm): a +20 % overshoot over
  the first millimetre or so of crushing, about 1-2 ms.
  ``peak_shape`` chooses among shapes that all differ from the law's own (jaxland's optional
  crush peak rises elastically and falls linearly, ``Honeycomb.peak_ratio1``): ``"bump"``
  (the default above), ``"exp"`` (a jump at the crush onset decaying as exp(-p / p0)) and
  ``"folds"`` (a fold-by-fold ripple, |cos(pi p / (2 p0))| exp(-p / (4 p0)): every wall fold
  re-peaks, decaying; rounded folds, where calibration's ``ripple`` form has linear ones)
  and ``"slow"`` (a bump that starts flat, u^2 exp(2 (1 - u)): the overshoot builds up
  slowly at first; no peak form of ``calibration`` is near it);
* ``peak_mode`` says where the crush peak acts. ``"sensor"`` (the default, and the bundled
  records'): the multiplier above on the two force channels only, a sensor-side artefact; the
  stroke and the body acceleration are those of the drop without a peak, so no honeycomb law
  reproduces every channel. ``"physical"``: the shape is tabulated into the truth's honeycomb
  as its strength excess (``Honeycomb.excess1``, ``physical_peak``), F1 (1 + CRUSH_PEAK s(c))
  against the crush c past the onset, so the simulated drop carries the peak in force, stroke
  and acceleration alike. There its length is ``PHYSICAL_PEAK_LENGTH_M`` (1.2 mm): with 0.4 mm
  the ``exp`` and ``folds`` shapes fall faster than half the ground stiffness, which the law
  refuses (the foot would snap through); ``peak_rise_m`` lets any shape build up linearly over
  that much crush first;
* optionally, **sensor low-pass filtering** (``lowpass_Hz``): every channel through a causal
  two-pole Butterworth filter at that corner frequency (an anti-aliasing / conditioning filter
  the model does not have; default off);
* optionally, **timing jitter** (``jitter_s``): each sample is taken at its nominal time plus
  a Gaussian error of this std (a jittery sampling clock; the record keeps the nominal axis);
* optionally, **another unloading law** in the truth itself: ``truth_vehicle(unload_ratio=)``
  (the secondary stage unloads along unload_ratio k_b3, ``Honeycomb.unload_ratio``).

``python -m calibration.virtual_rig --lab [--out data/synthetic]`` writes the bundled set: one
CSV + metadata TOML per drop height (``HEIGHTS_M``, with ``BUNDLED_ARTEFACTS`` on top of the
noise, offset and crush peak), the lab-format record ``drop_h0.20m_lab``
(``write_lab_drop_test``), ``truth_vehicle.toml`` (the truth, loadable by ``jaxland simulate
--config``), all labelled SYNTHETIC. ``--clean`` writes noise- and
artefact-free variants instead. Everything is seeded and reproducible.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import jaxland as jl

from ._data import CHANNELS, STANDARD_GRAVITY, DropTest
from ._filter import cfc_coefficients, filtfilt_np
from ._parameters import get_values, set_values
from ._report import atomic_write_text

__all__ = ["TRUTH_SCALE", "NOISE", "STROKE_OFFSET_M", "CRUSH_PEAK", "CRUSH_PEAK_LENGTH_M",
           "PHYSICAL_PEAK_LENGTH_M", "PEAK_MODES", "physical_peak", "HEIGHTS_M",
           "BUNDLED_ARTEFACTS", "LAB", "truth_vehicle", "record", "drop_test",
           "write_drop_test", "write_lab_drop_test", "main"]

# truth = paper vehicle x scale (ground stiffer and lossier-less, less damping, softer primary
# elastic stage, stronger primary and weaker secondary honeycomb)
TRUTH_SCALE = {"k": 1.30, "gamma": 0.80, "D_b": 0.80, "k_b1": 0.80, "F1": 1.08, "F2": 0.94}
NOISE = {"normal_force_N": 60.0, "buffer_force_N": 40.0, "stroke_m": 5e-5,
         "body_accel_mps2": 0.3}  # white-noise std per channel, in the channel's unit
STROKE_OFFSET_M = 1.5e-3
CRUSH_PEAK = 0.20
CRUSH_PEAK_LENGTH_M = 4e-4
PHYSICAL_PEAK_LENGTH_M = 1.2e-3  # the shapes' length p0 where the peak acts in the honeycomb
_TABLE_STEP = 0.1  # the physical peak's table: grid step, in peak lengths (folds' kinks on it)
_TABLE_SPAN = 30.0  # and its span (the shapes have decayed to < 1e-3 of the peak there)
HEIGHTS_M = (0.15, 0.20, 0.30)
# what the bundled drops carry beyond noise, the stroke offset and the crush peak: a jittery
# sampling clock and a sensor conditioning low-pass
BUNDLED_ARTEFACTS = {"jitter_s": 2e-6, "lowpass_Hz": 2000.0}
# the bundled lab-format record (``write_lab_drop_test``)
LAB = {"legs": (0, 1, 2, 3), "time_from_release": True, "specific_force": True, "cfc": 600,
       "peak_shape": "exp", "pre_trigger_s": 0.08, "jitter_s": 2e-6}
SAMPLE_RATE_HZ = 5000.0
PRE_TRIGGER_S = 0.05  # s of record before touchdown (``record``'s default)
_SIM_DT = 1e-5


def truth_vehicle(base: jl.Vehicle | None = None, *,
                  unload_ratio: float | None = None) -> jl.Vehicle:
    """The rig's truth: ``base`` (the paper vehicle) with ``TRUTH_SCALE`` applied (and, when
    given, the secondary stage's ``unload_ratio``: another unloading law)."""
    base = jl.paper_vehicle() if base is None else base
    names = tuple(TRUTH_SCALE)
    vals = get_values(base, names) * np.array([TRUTH_SCALE[n] for n in names])
    if unload_ratio is not None:
        names, vals = names + ("unload",), np.append(vals, float(unload_ratio))
    return jl.validate_vehicle(set_values(base, names, vals))


PEAK_SHAPES = ("bump", "exp", "folds", "slow")


def _crush_shape(p, shape: str = "bump"):
    """Relative force overshoot (peak 1) against the primary's crushed length p [m]."""
    u = np.maximum(p, 0.0) / CRUSH_PEAK_LENGTH_M
    if shape == "bump":
        return u * np.exp(1.0 - u)
    if shape == "exp":
        return np.where(p > 0.0, np.exp(-u), 0.0)
    if shape == "folds":
        return np.where(p > 0.0, np.abs(np.cos(0.5 * np.pi * u)) * np.exp(-0.25 * u), 0.0)
    if shape == "slow":
        return u * u * np.exp(2.0 * (1.0 - u))
    raise jl.ConfigError("peak_shape", shape, "must be one of " + ", ".join(PEAK_SHAPES))


PEAK_MODES = ("sensor", "physical")


def physical_peak(vehicle: jl.Vehicle, crush_peak: float = CRUSH_PEAK, shape: str = "bump", *,
                  length_m: float = PHYSICAL_PEAK_LENGTH_M,
                  rise_m: float = 0.0) -> jl.Vehicle:
    """``vehicle`` with a crush peak of the rig's ``shape`` in its honeycomb: the primary's
    strength excess (``Honeycomb.excess1``) crush_peak s(c / length_m) F1 against the crush c
    past its onset, s the shape of ``_crush_shape`` taken from the right at c = 0 (an ``exp``
    peak starts at its top); with ``rise_m`` > 0 the excess first rises linearly from 0 over
    that much crush to the shape's start, then follows the shape. Tabulated every
    ``_TABLE_STEP`` lengths over ``_TABLE_SPAN`` lengths (+ the rise); validated (a peak that
    rises faster than k_b1 or falls faster than half the ground stiffness is refused)."""
    _crush_shape(np.zeros(1), shape)  # refuses an unknown shape by name
    if not (np.isfinite(rise_m) and rise_m >= 0.0):
        raise jl.ConfigError("peak_rise_m", rise_m, "must be >= 0 m")
    if not (np.isfinite(length_m) and length_m > 0.0):
        raise jl.ConfigError("peak_length_m", length_m, "must be > 0 m")
    dc = _TABLE_STEP * length_m
    n = int(round((_TABLE_SPAN * length_m + rise_m) / dc))
    c = dc * np.arange(n)
    scale = CRUSH_PEAK_LENGTH_M / length_m  # _crush_shape's argument is in its own length
    after = np.maximum(c - rise_m, 1e-300)  # the shape from the right at its start
    s = _crush_shape(after * scale, shape)
    if rise_m > 0.0:
        start = float(_crush_shape(np.array([1e-300]), shape)[0])
        s = np.where(c < rise_m, start * c / rise_m, s)
    table = jnp.asarray(crush_peak * s, dtype=jnp.float64)
    return jl.validate_vehicle(eqx.tree_at(
        lambda v: (v.honeycomb.excess1, v.honeycomb.excess_length1), vehicle,
        (table, jnp.float64(n * dc)), is_leaf=lambda x: x is None))


def butterworth2(y: np.ndarray, corner_Hz: float, rate_Hz: float) -> np.ndarray:
    """Causal two-pole Butterworth low-pass (bilinear transform, pre-warped corner), started at
    rest on the first sample."""
    k = math.tan(math.pi * corner_Hz / rate_Hz)
    q = math.sqrt(2.0)
    norm = 1.0 / (1.0 + q * k + k * k)
    b0 = k * k * norm
    b1, b2 = 2.0 * b0, b0
    a1 = 2.0 * (k * k - 1.0) * norm
    a2 = (1.0 - q * k + k * k) * norm
    out = np.empty_like(y)
    x1 = x2 = y[0]
    y1 = y2 = y[0]
    for i, x in enumerate(y):
        v = b0 * x + b1 * x1 + b2 * x2 - a1 * y1 - a2 * y2
        x2, x1, y2, y1 = x1, x, y1, v
        out[i] = v
    return out


def record(vehicle: jl.Vehicle, drop_height_m: float, *, duration_s: float = 1.2,
           pre_trigger_s: float = PRE_TRIGGER_S, sample_rate_Hz: float = SAMPLE_RATE_HZ,
           noise: dict | None = NOISE, stroke_offset_m: float = STROKE_OFFSET_M,
           crush_peak: float = CRUSH_PEAK, channels=tuple(CHANNELS), seed: int = 0,
           lowpass_Hz: float | None = None, peak_shape: str = "bump", jitter_s: float = 0.0,
           legs=None, time_from_release: bool = False, specific_force: bool = False,
           cfc: int | None = None, peak_mode: str = "sensor",
           peak_length_m: float = PHYSICAL_PEAK_LENGTH_M, peak_rise_m: float = 0.0):
    """Run the rig: ``(time_s, {channel: samples}, info)``. ``noise=None``, ``stroke_offset_m=0``
    and ``crush_peak=0`` give the clean record (the model itself, sampled). ``lowpass_Hz``:
    filter every channel (before the noise, as a sensor's conditioning would) at this corner
    frequency [Hz] (None: no filter). ``peak_shape``: one of ``PEAK_SHAPES``. ``jitter_s``:
    std of the sampling-time error [s] (0: none). ``legs``: instrument these legs (a tuple of
    indices): the force and stroke channels are written per leg (``leg2_stroke_m``), each
    with its own noise and a stroke offset growing with the leg index (the drop is symmetric:
    every leg follows the same quarter model). ``time_from_release``: the time axis counts from
    release (the record still starts ``pre_trigger_s`` before touchdown: mid-fall; 0 puts its
    first sample at touchdown). ``specific_force``: the body channel is an accelerometer's
    specific force (0 in free fall). ``cfc``: the lab's SAE J211 filter of that class on every
    channel, after the noise (the record is delivered filtered). ``peak_mode``: one of
    ``PEAK_MODES``, ``"sensor"`` (the forces multiplied by the peak) or ``"physical"`` (the
    peak tabulated into ``vehicle``'s honeycomb by ``physical_peak`` with ``peak_length_m``
    and ``peak_rise_m``; ``info["truth_vehicle"]`` is the vehicle simulated)."""
    if peak_mode not in PEAK_MODES:
        raise jl.ConfigError("peak_mode", peak_mode, "must be one of " + ", ".join(PEAK_MODES))
    if peak_mode == "physical" and crush_peak != 0.0:
        vehicle = physical_peak(vehicle, crush_peak, peak_shape, length_m=peak_length_m,
                                rise_m=peak_rise_m)
    if not (np.isfinite(jitter_s) and 0.0 <= jitter_s < 0.25 / sample_rate_Hz):
        raise jl.ConfigError("jitter_s", jitter_s, f"must be in [0, {0.25 / sample_rate_Hz:g})"
                             " s (a quarter of the sampling interval)")
    _crush_shape(np.zeros(1), peak_shape)  # refuses an unknown shape by name
    if lowpass_Hz is not None and not (0 < lowpass_Hz < 0.5 * sample_rate_Hz):
        raise jl.ConfigError("lowpass_Hz", lowpass_Hz,
                             f"must be in (0, {0.5 * sample_rate_Hz:g}) Hz (below Nyquist)")
    step = int(round(1.0 / (sample_rate_Hz * _SIM_DT)))
    if abs(step * sample_rate_Hz * _SIM_DT - 1.0) > 1e-9:
        raise jl.ConfigError("sample_rate_Hz", sample_rate_Hz,
                             f"must divide 1/{_SIM_DT:g} s (the rig samples the simulation)")
    g = float(vehicle.g)
    t_td_est = math.sqrt(2.0 * drop_height_m / g)
    t_end = t_td_est + duration_s + 0.01
    res = jl.simulate(jl.Scene(drop_height=drop_height_m), vehicle, dt=_SIM_DT, t_end=t_end,
                      save_dt=_SIM_DT, model="quarter")
    tr = res.trajectory
    t_td = res.outcomes["touchdown_time_s"]
    i0 = int(round((t_td - pre_trigger_s) / _SIM_DT))
    n = int(round(duration_s * sample_rate_Hz))
    idx = i0 + step * np.arange(n)
    if i0 < 0 or idx[-1] >= tr["time_s"].size:
        raise jl.ConfigError("pre_trigger_s", pre_trigger_s, "the record must lie within the "
                             "simulated drop (pre-trigger shorter than the fall)")
    time_s = np.arange(n) / sample_rate_Hz + (i0 * _SIM_DT if time_from_release else 0.0)
    rng = np.random.default_rng(seed)
    if jitter_s > 0.0:  # sampled at jittered instants of the fine trajectory (linear interp.)
        t_fine = tr["time_s"]
        t_take = t_fine[idx] + rng.normal(0.0, jitter_s, size=n)

        def sample(col):
            return np.interp(t_take, t_fine, col)
    else:
        def sample(col):
            return col[idx]
    hc = vehicle.honeycomb
    p1 = np.minimum(sample(tr["plastic_set_m"]), float(hc.x_L2 - hc.x_L1))
    sensor_peak = crush_peak if peak_mode == "sensor" else 0.0
    peak = 1.0 + sensor_peak * _crush_shape(p1, peak_shape)
    out = {}
    series = [(c, None) for c in channels if legs is None or c == "body_accel_mps2"]
    if legs is not None:
        series += [(c, int(i)) for i in legs for c in channels if c != "body_accel_mps2"]
    for c, leg in series:
        y = np.array(sample(tr[CHANNELS[c][1]]), dtype=float)
        if c in ("normal_force_N", "buffer_force_N"):
            y = y * peak
        if c == "stroke_m":
            y = y + stroke_offset_m * (1.0 + 0.5 * (leg or 0))
        if c == "body_accel_mps2" and specific_force:
            y = y + float(vehicle.g)
        if lowpass_Hz is not None:
            y = butterworth2(y, lowpass_Hz, sample_rate_Hz)
        if noise:
            y = y + rng.normal(0.0, noise[c], size=n)
        if cfc is not None:
            y = filtfilt_np(y, cfc_coefficients(cfc, sample_rate_Hz))
        out[c if leg is None else f"leg{leg}_{c}"] = y
    info = dict(touchdown_time_in_record_s=float(t_td - i0 * _SIM_DT) + (
                    i0 * _SIM_DT if time_from_release else 0.0),
                release_time_in_record_s=0.0 if time_from_release else float(-i0 * _SIM_DT),
                touchdown_time_from_release_s=float(t_td),
                touchdown_speed_mps=float(res.outcomes["touchdown_speed_mps"]),
                max_stroke_m=float(res.outcomes["max_stroke_m"]),
                final_stroke_m=float(res.outcomes["final_stroke_m"]),
                peak_normal_force_N=float(res.outcomes["peak_normal_force_N"]),
                peak_strut_force_N=float(res.outcomes["peak_strut_force_N"]),
                peak_body_accel_mps2=float(res.outcomes["peak_body_accel_mps2"]),
                peak_mode=peak_mode, truth_vehicle=vehicle)
    return time_s, out, info


def drop_test(drop_height_m: float, *, vehicle: jl.Vehicle | None = None,
              nominal: jl.Vehicle | None = None, name: str | None = None, **kwargs) -> DropTest:
    """A validated, preprocessed in-memory ``DropTest`` from the rig (truth ``vehicle``,
    default ``truth_vehicle()``; the drop carries ``nominal``, default the paper vehicle, as its
    vehicle configuration, as a metadata file would). ``touchdown_time_s`` and
    ``release_time_s`` go to the metadata; the rest to ``record`` (a ``cfc`` there also sets
    the metadata's filter, as prefiltered; ``specific_force`` its accelerometer kind)."""
    vehicle = truth_vehicle() if vehicle is None else vehicle
    meta = {k: kwargs.pop(k) for k in ("touchdown_time_s", "release_time_s") if k in kwargs}
    t, ch, info = record(vehicle, drop_height_m, **kwargs)
    if kwargs.get("cfc") is not None:  # the lab delivered the record filtered
        meta.update(filter_cfc=kwargs["cfc"], filter_data_prefiltered=True)
    if kwargs.get("specific_force"):
        meta.update(body_accel_kind="specific_force")
    return DropTest.from_arrays(
        t, ch, sample_rate_Hz=kwargs.get("sample_rate_Hz", SAMPLE_RATE_HZ),
        drop_height_m=drop_height_m, vehicle=jl.paper_vehicle() if nominal is None else nominal,
        name=name or f"drop_h{drop_height_m:.2f}m", synthetic=True,
        description="SYNTHETIC (calibration.virtual_rig)", **meta)


def _drop_test_header(banner: str, flag: str, stem: str, drop_height_m: float) -> list:
    """The metadata lines every generated record starts with (``flag``: the generating
    command's option)."""
    return [
        f"# {banner}",
        f"# Generated by `python -m calibration.virtual_rig{flag}`; see data/README.md.",
        "[drop_test]",
        f'data_file = "{stem}.csv"',
        "synthetic = true",
        f'description = "{banner}"',
        f"drop_height_m = {drop_height_m}",
        f"sample_rate_Hz = {SAMPLE_RATE_HZ}",
    ]


def write_drop_test(out_dir, drop_height_m: float, *, vehicle=None, clean=False, seed=0,
                    vehicle_config="nominal_vehicle.toml", duration_s=1.2,
                    artefacts=BUNDLED_ARTEFACTS):
    """Write ``drop_hX.XXm.csv`` and ``.toml`` (metadata) into ``out_dir``; return their paths.
    ``vehicle_config`` is written into the metadata (the nominal vehicle the fit starts from).
    ``artefacts``: further ``record`` options beyond noise, offset and crush peak (default
    ``BUNDLED_ARTEFACTS``: sampling jitter and a sensor low-pass)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    vehicle = truth_vehicle() if vehicle is None else vehicle
    kw = dict(noise=None, stroke_offset_m=0.0, crush_peak=0.0) if clean else dict(artefacts)
    t, ch, info = record(vehicle, drop_height_m, duration_s=duration_s, seed=seed, **kw)
    stem = f"drop_h{drop_height_m:.2f}m{'_clean' if clean else ''}"
    banner = (f"SYNTHETIC drop test, not measured: calibration.virtual_rig, truth "
              f"truth_vehicle.toml, drop height {drop_height_m} m, seed {seed}"
              f"{', clean (no noise, offset or crush peak)' if clean else ''}")
    meta = [
        *_drop_test_header(banner, "", stem, drop_height_m),
        "sensor_leg = 0",
        f'vehicle_config = "{vehicle_config}"',
        "",
        "[synthetic_rig]  # what the rig did (informational; the loader does not read it)",
        f"seed = {seed}",
        "noise_std = { " + ", ".join(f"{k} = {0.0 if clean else v:g}"
                                     for k, v in NOISE.items()) + " }",
        f"stroke_offset_m = {0.0 if clean else STROKE_OFFSET_M:g}",
        f"crush_peak_rel = {0.0 if clean else CRUSH_PEAK:g}",
        f"crush_peak_length_m = {CRUSH_PEAK_LENGTH_M:g}",
        *(f"{k} = {_toml_value(v)}" for k, v in ({} if clean else artefacts).items()),
        f"touchdown_time_in_record_s = {info['touchdown_time_in_record_s']:.6f}",
        f"touchdown_speed_mps = {info['touchdown_speed_mps']:.9g}",
        f"true_max_stroke_m = {info['max_stroke_m']:.9g}",
        f"true_final_stroke_m = {info['final_stroke_m']:.9g}",
        f"true_peak_normal_force_N = {info['peak_normal_force_N']:.9g}",
        f"true_peak_buffer_force_N = {info['peak_strut_force_N']:.9g}",
        f"true_peak_body_accel_mps2 = {info['peak_body_accel_mps2']:.9g}",
    ]
    csv_path, meta_path = out_dir / f"{stem}.csv", out_dir / f"{stem}.toml"
    jl.atomic_write_csv(csv_path, {"time_s": t, **ch}, digits=7, comments=[banner])
    atomic_write_text(meta_path, "\n".join(meta) + "\n")
    return csv_path, meta_path


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return f"{v:g}"


def write_lab_drop_test(out_dir, drop_height_m: float = 0.2, *, vehicle=None, seed=0,
                        vehicle_config="nominal_vehicle.toml", duration_s=0.6):
    """``drop_hX.XXm_lab.{csv,toml}``: a record as a lab writes it (``LAB``): four
    instrumented legs, lab units (ms, kN, mm, g), the body channel an accelerometer's
    specific force, the time axis from release with the record starting mid-fall, the whole
    record delivered CFC 600 filtered; and a crush peak of another shape (``exp``). Its
    metadata says so (``release_time_s``, ``body_accel_kind``, ``filter_cfc``,
    ``filter_data_prefiltered``), and its drop height is checked against the free fall."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    vehicle = truth_vehicle() if vehicle is None else vehicle
    t, ch, info = record(vehicle, drop_height_m, duration_s=duration_s, seed=seed, **LAB)
    cols = {"time_ms": t * 1e3}
    units = {"normal_force_N": ("normal_force_kN", 1e-3), "buffer_force_N":
             ("buffer_force_kN", 1e-3), "stroke_m": ("stroke_mm", 1e3)}
    for c, y in ch.items():
        if c == "body_accel_mps2":
            cols["body_accel_g"] = y / STANDARD_GRAVITY
            continue
        leg, base = c.split("_", 1)
        name, factor = units[base]
        cols[f"{leg}_{name}"] = y * factor
    stem = f"drop_h{drop_height_m:.2f}m_lab"
    banner = (f"SYNTHETIC drop test, not measured: calibration.virtual_rig (lab format), truth "
              f"truth_vehicle.toml, drop height {drop_height_m} m, seed {seed}")
    meta = [
        *_drop_test_header(banner, " --lab", stem, drop_height_m),
        f'vehicle_config = "{vehicle_config}"',
        "release_time_s = 0.0",
        'body_accel_kind = "specific_force"',
        f"filter_cfc = {LAB['cfc']}",
        "filter_data_prefiltered = true",
        "",
        "[synthetic_rig]  # what the rig did (informational; the loader does not read it)",
        f"seed = {seed}",
        "noise_std = { " + ", ".join(f"{k} = {v:g}" for k, v in NOISE.items()) + " }",
        f"stroke_offset_m = {STROKE_OFFSET_M:g}  # x (1 + 0.5 leg index)",
        f"crush_peak_rel = {CRUSH_PEAK:g}",
        f"crush_peak_length_m = {CRUSH_PEAK_LENGTH_M:g}",
        *(f"{k} = {_toml_value(v)}" for k, v in LAB.items()),
        f"touchdown_time_in_record_s = {info['touchdown_time_in_record_s']:.6f}",
        f"touchdown_speed_mps = {info['touchdown_speed_mps']:.9g}",
        f"true_max_stroke_m = {info['max_stroke_m']:.9g}",
        f"true_final_stroke_m = {info['final_stroke_m']:.9g}",
    ]
    csv_path, meta_path = out_dir / f"{stem}.csv", out_dir / f"{stem}.toml"
    jl.atomic_write_csv(csv_path, cols, digits=7, comments=[banner])
    atomic_write_text(meta_path, "\n".join(meta) + "\n")
    return csv_path, meta_path


def write_nominal(out_dir) -> Path:
    """``nominal_vehicle.toml``: the vehicle as designed (the paper's), which the drop tests'
    metadata name as their configuration and a fit starts from."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "nominal_vehicle.toml"
    atomic_write_text(path, "# The nominal (as designed) vehicle of the synthetic drop tests: the "
                 "paper vehicle.\n" + jl.vehicle_to_toml(jl.paper_vehicle()))
    return path


def write_truth(out_dir, vehicle=None) -> Path:
    """``truth_vehicle.toml``: the rig's truth as a jaxland vehicle config, labelled."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    vehicle = truth_vehicle() if vehicle is None else vehicle
    head = ["# SYNTHETIC: the TRUE parameters of the virtual test rig (calibration.virtual_rig),",
            "# the paper vehicle scaled by " + ", ".join(f"{k} x{v:g}" for k, v in
                                                       TRUTH_SCALE.items()) + ".",
            "# A calibration of data/synthetic/*.csv should recover these.", ""]
    path = out_dir / "truth_vehicle.toml"
    atomic_write_text(path, "\n".join(head) + jl.vehicle_to_toml(vehicle))
    return path


# the files the rig writes into its folder (``main``): a folder holding others is not its own
_RIG_FILES = re.compile(r"(drop_h\d+\.\d+m\w*\.(csv|toml)|\w+_vehicle\.toml)")


def _check_args(args) -> None:
    """The command line's values, refused by name before anything is simulated or written."""
    from ._data import MIN_AFTER_S

    for h in args.heights:
        if not (math.isfinite(h) and h > 0.0):
            raise jl.ConfigError("--heights", h, "each must be a drop height > 0 m")
    pre = PRE_TRIGGER_S
    if not (math.isfinite(args.duration) and args.duration > pre + MIN_AFTER_S):
        raise jl.ConfigError("--duration", args.duration, f"must be > {pre + MIN_AFTER_S:g} s: "
                             f"a record starts {pre:g} s before touchdown and a drop test needs "
                             f">= {MIN_AFTER_S:g} s after it")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise jl.ConfigError("--out", str(out), "exists and is not a folder")
    foreign = sorted(c.name for c in out.iterdir() if not c.name.startswith(".")
                     and not _RIG_FILES.fullmatch(c.name)) if out.is_dir() else []
    if foreign:
        raise jl.ConfigError("--out", str(out), f"holds files the rig does not write "
                             f"({', '.join(foreign[:3])}): give a new folder or the rig's own")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m calibration.virtual_rig",
                                description="write synthetic drop tests with known truth")
    p.add_argument("--out", default="data/synthetic", help="output folder")
    p.add_argument("--heights", type=float, nargs="+", default=list(HEIGHTS_M),
                   help="drop heights [m]")
    p.add_argument("--clean", action="store_true", help="no noise, offset or crush peak")
    p.add_argument("--duration", type=float, default=1.2, help="record length [s]")
    p.add_argument("--lab", action="store_true",
                   help="also write the lab-format record drop_h0.20m_lab (legs, lab units, "
                        "release time, CFC 600)")
    args = p.parse_args(argv)
    try:
        _check_args(args)
        write_truth(args.out)
        write_nominal(args.out)
        for i, h in enumerate(args.heights):
            paths = write_drop_test(args.out, h, clean=args.clean, seed=100 + i,
                                    duration_s=args.duration)
            print(f"wrote {paths[0]} and {paths[1].name}")
        if args.lab:
            paths = write_lab_drop_test(args.out, 0.2, seed=200)
            print(f"wrote {paths[0]} and {paths[1].name}")
    except jl.JaxlandError as err:
        print(f"virtual_rig: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
