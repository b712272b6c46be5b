"""Prediction check: simulate a drop with a (fitted) vehicle and compare the outcomes an engineer
reads off a drop test with the data.

The model runs the whole record (``jaxland.simulate``, validated, numerics checked) from
touchdown at the drop's touchdown speed, sampled every 1e-5 s and aligned at the detected
touchdown. Compared quantities (data: offset-corrected samples; model: its trajectory over the
same time span):

* ``peak_normal_force_N``, ``peak_buffer_force_N``, ``peak_body_accel_mps2``: largest value;
* ``max_stroke_m``: largest stroke;
* ``final_stroke_m``: mean stroke over the last ``FINAL_SPAN_S`` of the record.

Each leg's series gets its own metrics (``leg2_max_stroke_m``). A series with a CFC filter in
the metadata is compared filtered alike: the model at the sample times, filtered as the data.

Relative error = (model - data) / |data|. The paper's own experiment was matched to 9.9 % and
19.72 % on peaks and 0.28 % on the steady stroke. The data's peaks include its noise (a few
noise standard deviations) and any artefact the model does not have (a crush peak).
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import jaxland as jl
from jaxland._files import json_text

from ._data import CHANNELS, DropTest, base_channel, check_same_article
from ._filter import filtfilt_np

__all__ = ["Prediction", "predict", "PAPER_ERRORS", "read_fit_status", "check_model_step"]

FINAL_SPAN_S = 0.02
MODEL_DT = 1e-5  # s: the model's step (euler), jaxland fit's default step
MODEL_SAVE_DT = 1e-5
PAPER_ERRORS = {"peak (paper, experiment vs simulation)": [0.099, 0.1972],
                "steady stroke (paper)": 0.0028}
# metric -> (channel, reducer)
METRICS = {
    "peak_normal_force_N": ("normal_force_N", "max"),
    "peak_buffer_force_N": ("buffer_force_N", "max"),
    "max_stroke_m": ("stroke_m", "max"),
    "final_stroke_m": ("stroke_m", "final"),
    "peak_body_accel_mps2": ("body_accel_mps2", "max"),
}


@dataclass
class Prediction:
    """Result of ``predict``: per metric the data value, the model value and the relative
    error; plus the model traces at full resolution for plots."""

    drop: DropTest = field(repr=False)
    metrics: dict
    model_time_s: np.ndarray = field(repr=False)
    model: dict = field(repr=False)
    touchdown_time_s: float = 0.0
    inputs: dict = field(default_factory=dict)  # what a caller ran it from (the CLI's files)
    fit_status: dict | None = None  # read_fit_status of the vehicle file (the CLI's)

    def to_dict(self) -> dict:
        return dict(drop=self.drop.summary(), touchdown_time_s=self.touchdown_time_s,
                    **({"inputs": self.inputs} if self.inputs else {}),
                    **({"fit_status": self.fit_status} if self.fit_status else {}),
                    metrics=self.metrics, paper_errors=PAPER_ERRORS,
                    note="relative error = (model - data) / |data|; data peaks include noise "
                         "and any artefact the model lacks (e.g. a honeycomb crush peak)")

    def to_json(self, path) -> Path:
        from ._report import atomic_write_text

        return atomic_write_text(Path(path), json_text(self.to_dict()))

    def plot(self, path) -> Path:
        from ._plots import plot_prediction

        return plot_prediction(self, Path(path))


def model_record(vehicle: jl.Vehicle, drop: DropTest, t_end_s: float | None = None):
    """(model time after touchdown [s], {channel: model trace}) for ``drop``'s channels."""
    t_end = drop.duration_after_touchdown_s + 2 * MODEL_SAVE_DT if t_end_s is None else t_end_s
    t_end = round(t_end / MODEL_SAVE_DT) * MODEL_SAVE_DT + MODEL_SAVE_DT
    res = jl.simulate(jl.Scene.from_touchdown_speed(drop.touchdown_speed_mps), vehicle,
                      dt=MODEL_DT, t_end=t_end, save_dt=MODEL_SAVE_DT, model="quarter")
    tr = res.trajectory
    return np.asarray(tr["time_s"]), {c: np.asarray(tr[CHANNELS[c][1]]) for c in CHANNELS}


def check_model_step(vehicle: jl.Vehicle, where: str = "vehicle") -> None:
    """Refuse a vehicle (named ``where``, e.g. ``--config FILE``) whose stability limit (euler,
    quarter model: ``jaxland.stable_step``) lies below ``MODEL_DT``, the step predict simulates
    at, naming its key (as its TOML writes it) that sets the limit: the one whose paper value
    raises the limit most (a stiffness in N/mm under an _N_per_m key, a mass in t under a _kg
    key). predict offers no step to change: the value is the one to check."""
    limit = float(jl.stable_step(vehicle))
    if limit >= MODEL_DT:
        return
    mine = tomllib.loads(jl.vehicle_to_toml(vehicle))
    paper = tomllib.loads(jl.vehicle_to_toml(jl.paper_vehicle()))
    best = None
    for section, table in mine.items():
        for key, val in table.items():
            usual = paper.get(section, {}).get(key)
            if isinstance(val, (bool, str, dict)) or usual is None or val == usual:
                continue
            trial = {sec: dict(tab) for sec, tab in mine.items()}
            trial[section][key] = usual
            try:
                lim = float(jl.stable_step(jl.vehicle_from_dict(trial, validate=False)))
            except (jl.ConfigError, ValueError, TypeError):
                continue
            if best is None or lim > best[0]:
                best = (lim, section, key, val, usual)
    step = (f"below the step {MODEL_DT:g} s predict simulates at (euler, the quarter model; "
            "jaxland fit's default step)")
    if best is None or best[0] <= limit:
        raise jl.ConfigError(where, f"stability limit {limit:.3g} s", f"is {step}: check the "
                             "vehicle's stiffnesses, masses and damping")
    lim, section, key, val, usual = best
    try:
        times = f"{float(np.max(val)) / float(np.max(usual)):.3g} x "
    except (TypeError, ValueError, ZeroDivisionError):
        times = ""
    raise jl.ConfigError(f"{where}: {section}.{key}", val, f"is {times}the paper vehicle's "
                         f"{usual!r} and puts the vehicle's stability limit at {limit:.3g} s "
                         f"(with the paper's value {lim:.3g} s), {step}: check the value and "
                         "its unit")


def predict(vehicle: jl.Vehicle, drop: DropTest, *, touchdown_time_s: float | None = None
            ) -> Prediction:
    """Simulate ``drop`` with ``vehicle`` and compare peaks, max and final stroke. A drop whose
    metadata names a ``vehicle_config`` is refused with a ``vehicle`` of another article
    (``check_same_article``: it may differ only in the calibrated parameters), and so is a
    vehicle too stiff for the model's step (``check_model_step``)."""
    jl.validate_vehicle(vehicle)
    check_model_step(vehicle)
    if drop.vehicle_config:
        check_same_article(drop.vehicle, vehicle,
                           f"{drop.name}: vehicle_config {drop.vehicle_config}")
    t0 = drop.touchdown_time_s if touchdown_time_s is None else float(touchdown_time_s)
    tm, model = model_record(vehicle, drop, drop.time_s[-1] - t0)
    data = drop.corrected
    t_rel = drop.time_s - t0
    in_rec = tm <= t_rel[-1]
    metrics = {}
    for name, (chan, how) in METRICS.items():
        for col in (c for c in data if base_channel(c) == chan):
            y, m, t_m = data[col], model[chan][in_rec], tm[in_rec]
            if col in drop.filters:  # J211 alike on both: the model at the samples, filtered
                coeffs = drop.filter_coefficients(col)
                m, t_m = filtfilt_np(np.interp(t_rel, tm, model[chan]), coeffs), t_rel
                if not drop.filter_data_prefiltered:
                    y = filtfilt_np(y, coeffs)
            if how == "max":
                dv, mv = float(np.max(y)), float(np.max(m))
            else:
                t_from = t_rel[-1] - FINAL_SPAN_S
                dv = float(np.mean(y[t_rel >= t_from]))
                mv = float(np.mean(m[t_m >= t_from]))
            key = (col[: -len(chan)] if col != chan else "") + name  # leg2_max_stroke_m
            metrics[key] = dict(data=dv, model=mv, rel_error=(mv - dv) / abs(dv))
    return Prediction(drop, metrics, tm, model, t0)


NO_BAND = ("not propagated: the model's traces and metrics are for the fitted values alone, "
           "with no uncertainty band; parameters holds each value's standard error as the fit "
           "reported it (its fit_report.json holds their correlation)")
_ENTRY = re.compile(r"(?P<name>[A-Za-z_]\w*) = (?P<value>[^\s,]+)(?: \+/- (?P<se>[^\s,]+))? "
                    r"(?P<unit>[^\s,(]+)(?: \((?P<note>[^)]*)\))?")


def _number(text: str | None) -> float | None:
    try:
        x = float(text)
    except (TypeError, ValueError):
        return None
    return x if np.isfinite(x) else None


def config_header(path) -> list[str]:
    """The comment block of a vehicle file before its first TOML line (where ``jaxland fit``
    writes what it says of the fit)."""
    head = []
    for line in jl.read_text(path, "config").splitlines():
        if line.strip() and not line.startswith("#"):
            break
        head.append(line.rstrip())
    return head


def read_fit_status(path, vehicle: jl.Vehicle | None = None) -> dict:
    """What the header of a vehicle file written by ``jaxland fit`` (``fitted_vehicle.toml``,
    ``FitResult.to_toml``) says of its fit: ``{"from_fit": False}`` for a file without that
    header; else ``from_fit``, ``fitted_against`` (the records), ``sound`` (no flag),
    ``flags`` (``MISFIT``, ``NOT CONVERGED``, ``NO TRUSTED INTERVAL``, each CAUTION's flag,
    and a parameter ``NOT IDENTIFIED`` or ``AT A BOUND``), the ``misfit``, ``not_converged``
    and ``interval_not_bounded`` lines' text (None where absent), ``cautions`` ({flag:
    text}), the
    ``interval`` the errors are, ``parameters`` (``{name: {value, std_error,
    rel_std_error, unit, note}}``, the header's rounded numbers; std_error None where the
    fit gave none) and ``uncertainty`` (how far the prediction carries it: not at all).

    With ``vehicle`` (the file as loaded), ``edited`` lists each fitted value, and each value
    the fit held (``held``: true), that the file now holds differently from its header
    (``edited_since_fit``); an edited file is not sound and carries the flag ``EDITED SINCE
    THE FIT: <name>``: its predictions are not the fit's."""
    from ._fit import (
        AT_BOUND,
        HEADER_ARTICLE,
        HEADER_CAUTION,
        HEADER_FIT,
        HEADER_HELD,
        HEADER_MISFIT,
        HEADER_NOT_BOUNDED,
        HEADER_NOT_CONVERGED,
        HEADER_OFF,
        HEADER_VALUES,
        NOT_IDENTIFIED,
    )

    head = config_header(path)

    def after(prefix: str) -> str | None:  # the text of the header line with this prefix
        return next((x[len(prefix):] for x in head if x.startswith(prefix)), None)

    against = after(HEADER_FIT)
    if against is None:
        return {"from_fit": False}
    values_head = HEADER_VALUES.split("{interval}")
    values = next((x for x in head if x.startswith(values_head[0])), None)
    interval, params = None, {}
    if values is not None:
        interval, _, entries = values[len(values_head[0]):].partition(values_head[1])
        for m in _ENTRY.finditer(entries):
            v, se = _number(m["value"]), _number(m["se"])
            params[m["name"]] = dict(
                value=v, std_error=se, unit=m["unit"], note=m["note"],
                rel_std_error=None if se is None or not v else se / abs(v))
    held = {m["name"]: dict(value=_number(m["value"]), unit=m["unit"])
            for m in _ENTRY.finditer(after(HEADER_HELD) or "")}
    misfit, capped = after(HEADER_MISFIT), after(HEADER_NOT_CONVERGED)
    unbounded = after(HEADER_NOT_BOUNDED)
    before, after_flag = HEADER_CAUTION.split("{flag}")
    cautions = dict(x[len(before):].split(after_flag, 1) for x in head if x.startswith(before))
    flags = (["MISFIT"] if misfit is not None else []) + (
        ["NOT CONVERGED"] if capped is not None else []) + (
        ["NO TRUSTED INTERVAL"] if unbounded is not None else []) + list(cautions) + [
        f"{'NOT IDENTIFIED' if NOT_IDENTIFIED in p['note'] else 'AT A BOUND'}: {n}"
        for n, p in params.items() if p["note"] and (NOT_IDENTIFIED in p["note"]
                                                      or AT_BOUND in p["note"])]
    off = [n.strip() for n in (after(HEADER_OFF) or "").split(",") if n.strip()]
    edited = [] if vehicle is None else (
        edited_since_fit(params, vehicle)
        + [dict(e, held=True) for e in edited_since_fit(held, vehicle)]
        + switched_on_since_fit(off, vehicle))
    article = (after(HEADER_ARTICLE) or "").strip()
    if vehicle is not None and article:
        from ._data import article_fingerprint

        if article_fingerprint(vehicle) != article:  # a mass, a length, a peak's table
            edited.append(dict(name="article", key=None, file=None, fitted=None, unit=None,
                               article=True))
    flags += [f"{EDITED}: {e['name']}" for e in edited]
    return dict(from_fit=True, fitted_against=against, sound=not flags, flags=flags,
                misfit=misfit, not_converged=capped, interval_not_bounded=unbounded,
                cautions=cautions,
                interval=interval or None,
                parameters=params, uncertainty=NO_BAND,
                **({} if vehicle is None else {"edited": edited}))


EDITED = "EDITED SINCE THE FIT"


def switched_on_since_fit(off, vehicle: jl.Vehicle) -> list[dict]:
    """The law's extensions the fit held off (``off``: the header's names) that ``vehicle``
    has on: one ``{name, key, file, fitted: None, unit, held: True, off_in_fit: True}`` each,
    ``file`` in the key's units."""
    from ._parameters import EXTENSION_OF, PARAMS, acts_in

    out = []
    for name in off:
        if name not in PARAMS or not acts_in(name, vehicle):
            continue
        if EXTENSION_OF.get(name) in off:
            continue  # its peak is switched on, and named
        _, unit, key, *_ = PARAMS[name]
        held = PARAMS[name][0](vehicle)
        if np.ndim(held) != 0:
            continue
        file, unit = _in_key_units(key, float(held), unit)
        out.append(dict(name=name, key=key, file=file, fitted=None, unit=unit, held=True,
                        off_in_fit=True))
    return out


def _in_key_units(key: str, value_si: float, unit: str) -> tuple[float, str]:
    """An SI value in its TOML key's units (mm for a ``_mm`` key, else SI), to the header's
    6 significant digits, with that unit."""
    if key.endswith("_mm"):
        return float(f"{value_si * 1e3:.6g}"), "mm"
    return float(f"{value_si:.6g}"), unit


def edited_since_fit(params: dict, vehicle: jl.Vehicle) -> list[dict]:
    """The fitted values (``read_fit_status``'s ``parameters``, as the header printed them,
    6 significant digits) that ``vehicle`` holds differently at the header's precision: one
    ``{name, key, file, fitted, unit}`` per value, ``key`` the TOML key and ``file`` /
    ``fitted`` in its units. A value the file does not hold as that key (an extension that is
    off there, e.g. the crush peak of a fit with the peak on the force channels, or an
    exponential peak's table) is not compared."""
    from ._parameters import PARAMS

    out = []
    for name, p in params.items():
        if name not in PARAMS or p["value"] is None:
            continue
        getter, _, key, *_ = PARAMS[name]
        held = getter(vehicle)
        if held is None or np.ndim(held) != 0:
            continue
        held, v = float(held), p["value"]
        # the header's last printed digit, half of it either side (and rounding's noise)
        half = 0.5 * 10.0 ** (math.floor(math.log10(abs(v))) - 5) if v else 0.0
        if abs(held - v) <= half * (1.0 + 1e-6) + 1e-300:
            continue
        file, unit = _in_key_units(key, held, p["unit"])
        out.append(dict(name=name, key=key, file=file,
                        fitted=_in_key_units(key, p["value"], p["unit"])[0], unit=unit))
    return out
