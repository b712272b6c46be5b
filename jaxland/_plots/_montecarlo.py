"""Monte Carlo figures: outcome histograms, envelopes (empirical CDFs) and a tip-over map over the
two most influential inputs. matplotlib is imported only inside the functions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._montecarlo._stats import all_landings_text, probability_text, ranked_inputs
from .._solvers import FAILED_CODES, Result
from ._landing import _save

_OUTCOMES = (  # (label, function of (outputs) -> per-sample values, scale, unit)
    ("max stroke, any leg", lambda o: o["max_stroke_m"].max(axis=1), 1e3, "mm"),
    ("peak body acceleration", lambda o: o["peak_body_accel_mps2"], 1.0, "m/s^2"),
    ("peak strut force, any leg", lambda o: o["peak_strut_force_N"].max(axis=1), 1e-3, "kN"),
    ("foot slip, any leg", lambda o: o["slip_distance_m"].max(axis=1), 1e3, "mm"),
)


def _outcomes(result):
    rows = list(_OUTCOMES)
    if "min_stability_margin_m" in result.outputs:
        rows.append(("min stability margin", lambda o: o["min_stability_margin_m"], 1.0, "m"))
    return rows


def _input_column(result, name):
    """An input by its name in ``ranked_inputs`` (``plateau_scale[leg2]`` selects a leg)."""
    base, _, leg = name.partition("[leg")
    arr = np.asarray(result.inputs[base], dtype=float)
    return arr[:, int(leg.rstrip("]"))] if leg else arr


def _kinds(result) -> list[tuple[str, np.ndarray, dict]]:
    """The samples the tip-over map draws apart, as (label, mask, scatter style): successful
    landings stable or tipped; numerical failures (``Result.failed``); landings that t_end cut
    off (UNFINISHED: no final outcome, not tip-over-free) and landings without touchdown,
    neither of them failures (the summary's ``n_unfinished`` and ``n_no_touchdown``)."""
    code = np.asarray(result.failure)
    ok = code == int(Result.SUCCESSFUL)
    tipped = np.asarray(result.outputs["tipped_over"], dtype=bool)
    return [
        ("stable", ok & ~tipped, dict(s=10, c="C0")),
        ("tipped", ok & tipped, dict(s=14, c="C3", marker="x")),
        ("unfinished, no final outcome", code == int(Result.UNFINISHED),
         dict(s=18, facecolors="none", edgecolors="C1", marker="o")),
        ("no touchdown", code == int(Result.NO_TOUCHDOWN), dict(s=16, c="0.5", marker="v")),
        ("failed", np.isin(code, FAILED_CODES), dict(s=14, c="k", marker="s")),
    ]


def _counts_text(s: dict) -> str:
    """The landings by how they ended, as the summary counts them."""
    extra = [f"{s[key]} {name}" for key, name in (("n_unfinished", "unfinished"),
                                                  ("n_no_touchdown", "without touchdown"))
             if s[key]]
    return ", ".join([f"{s['n_succeeded']} successful", f"{s['n_failed']} failed", *extra])


def plot_montecarlo(result, out_dir) -> list[Path]:
    """Write mc_histograms.png, mc_envelopes.png and (when the model can tip over and there
    are two or more dispersed inputs) mc_tipover_map.png into ``out_dir``."""
    from matplotlib.figure import Figure

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ok = result.failure == 0  # Result.SUCCESSFUL
    rows = _outcomes(result)
    s = result.summary
    tippable = s["tip_over"].get("modelled", True)  # the quarter model cannot tip
    # each probability with where it lies over all landings: over the successful ones alone
    # it is biased where some are unfinished or failed
    tip = (f"P(tip-over) = {probability_text(s['tip_over'])}"
           f"{all_landings_text(s['tip_over'])}" if tippable else "tip-over not modelled")
    title = (f"{s['n']} landings ({s['model']} model): {_counts_text(s)};\n{tip};\n"
             f"P(bottoming) = {probability_text(s['bottoming'])}"
             f"{all_landings_text(s['bottoming'])}")
    paths = []

    fig = Figure(figsize=(4.2 * len(rows), 3.6), layout="constrained")
    for ax, (label, fn, scale, unit) in zip(fig.subplots(1, len(rows)), rows):
        x = np.asarray(fn(result.outputs), dtype=float)[ok] * scale
        ax.hist(x, bins=min(50, max(5, int(np.sqrt(x.size)))), color="C0")
        ax.set_xlabel(f"{label} [{unit}]")
        ax.set_ylabel("successful landings")
        if unit == "m" and "margin" in label:
            ax.axvline(0.0, color="r", ls="--", label="tip-over")
            ax.legend()
    fig.suptitle(title)
    paths.append(_save(fig, out_dir / "mc_histograms.png"))

    fig = Figure(figsize=(4.2 * len(rows), 3.6), layout="constrained")
    for ax, (label, fn, scale, unit) in zip(fig.subplots(1, len(rows)), rows):
        x = np.sort(np.asarray(fn(result.outputs), dtype=float)[ok] * scale)
        ax.plot(x, np.arange(1, x.size + 1) / max(x.size, 1), color="C1")
        for q in (0.05, 0.5, 0.95, 0.99):
            ax.axhline(q, color="0.8", lw=0.8)
        ax.set_xlabel(f"{label} [{unit}]")
        ax.set_ylabel("fraction of landings below")
    fig.suptitle(f"envelopes (empirical CDFs) over the {s['n_succeeded']} successful "
                 "landings; lines at 5, 50, 95, 99 %")
    paths.append(_save(fig, out_dir / "mc_envelopes.png"))

    ranked = ranked_inputs(s["sensitivity"]["ranking"])
    if len(ranked) >= 2 and tippable:
        a, b = ranked[:2]
        xa, xb = _input_column(result, a), _input_column(result, b)
        fig = Figure(figsize=(6.5, 5), layout="constrained")
        ax = fig.subplots()
        for label, mask, style in _kinds(result):
            if label in ("stable", "tipped") or mask.any():
                ax.scatter(xa[mask], xb[mask], label=f"{label} ({int(mask.sum())})", **style)
        ax.set_xlabel(a)
        ax.set_ylabel(b)
        ax.set_title(f"tip-over map over the two most influential inputs\n(by effect on "
                     f"{s['sensitivity']['target']})\n{s['n']} landings: {_counts_text(s)}")
        ax.legend()
        paths.append(_save(fig, out_dir / "mc_tipover_map.png"))
    return paths
