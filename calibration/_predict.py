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

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import jaxland as jl

from ._data import CHANNELS, DropTest, base_channel
from ._filter import filtfilt_np

__all__ = ["Prediction", "predict", "PAPER_ERRORS"]

FINAL_SPAN_S = 0.02
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

    def to_dict(self) -> dict:
        return dict(drop=self.drop.summary(), touchdown_time_s=self.touchdown_time_s,
                    **({"inputs": self.inputs} if self.inputs else {}),
                    metrics=self.metrics, paper_errors=PAPER_ERRORS,
                    note="relative error = (model - data) / |data|; data peaks include noise "
                         "and any artefact the model lacks (e.g. a honeycomb crush peak)")

    def to_json(self, path) -> Path:
        from ._report import atomic_write_text

        return atomic_write_text(Path(path), json.dumps(self.to_dict(), indent=2) + "\n")

    def max_abs_error(self, kind: str = "all") -> float:
        keys = [k for k in self.metrics if kind == "all" or kind in k]
        return max(abs(self.metrics[k]["rel_error"]) for k in keys)

    def plot(self, path) -> Path:
        from ._plots import plot_prediction

        return plot_prediction(self, Path(path))


def model_record(vehicle: jl.Vehicle, drop: DropTest, t_end_s: float | None = None):
    """(model time after touchdown [s], {channel: model trace}) for ``drop``'s channels."""
    t_end = drop.duration_after_touchdown_s + 2 * MODEL_SAVE_DT if t_end_s is None else t_end_s
    t_end = round(t_end / MODEL_SAVE_DT) * MODEL_SAVE_DT + MODEL_SAVE_DT
    res = jl.simulate(jl.Scene.from_touchdown_speed(drop.touchdown_speed_mps), vehicle,
                      dt=1e-5, t_end=t_end, save_dt=MODEL_SAVE_DT, model="quarter")
    tr = res.trajectory
    return np.asarray(tr["time_s"]), {c: np.asarray(tr[CHANNELS[c][1]]) for c in CHANNELS}


def predict(vehicle: jl.Vehicle, drop: DropTest, *, touchdown_time_s: float | None = None
            ) -> Prediction:
    """Simulate ``drop`` with ``vehicle`` and compare peaks, max and final stroke."""
    jl.validate_vehicle(vehicle)
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
