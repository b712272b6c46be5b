"""Design figures: optimisation histories, honeycomb force-stroke curves before/after, and the
verification Monte Carlo's outcome distributions before/after. matplotlib is imported only
inside the functions, through its object-oriented API."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._montecarlo._stats import probability_text
from ._landing import _save

__all__ = ["plot_design"]


def _figure(**kw):
    from matplotlib.figure import Figure

    return Figure(layout="constrained", **kw)


def plot_design(result, out_dir: Path) -> list[Path]:
    """Write design_history.png, design_force_stroke.png and (after ``verify_design``)
    design_outcomes.png into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [_history(result, out_dir / "design_history.png"),
             _force_stroke(result, out_dir / "design_force_stroke.png")]
    if result.mc_before is not None and result.mc_after is not None:
        paths.append(_outcomes(result, out_dir / "design_outcomes.png"))
    return paths


def _history(result, path: Path) -> Path:
    h = result.history
    it = np.array([r["iteration"] for r in h])
    fig = _figure(figsize=(14, 3.8))
    ax1, ax2, ax3 = fig.subplots(1, 3)
    obj = result.spec.objective
    label = {"cvar": f"CVaR{obj.level:g}", "normal": f"normal q{obj.level:g}"}.get(obj.measure,
                                                                              obj.measure)
    ax1.plot(it, [r["objective_measure_mps2"] for r in h], color="C0")
    ax1.set_xlabel("iteration")
    ax1.set_ylabel(f"{label} of peak body acceleration [m/s^2]")
    ax1b = ax1.twinx()
    ax1b.plot(it, [r["gear_mass_kg"] for r in h], color="C1", ls="--")
    ax1b.set_ylabel("gear mass proxy [kg]", color="C1")
    ax1.set_title("objective")
    for c in result.spec.constraints:
        m = c.measure if c.measure in ("mean", "max") else f"{c.measure} {c.level:g}"
        ax2.plot(it, [r["constraints"][c.name] for r in h], label=f"{c.name} ({m})")
    ax2.axhline(0.0, color="k", lw=0.8)
    ax2.set_xlabel("iteration")
    ax2.set_ylabel("constraint g = R[badness] / scale [1]\n(feasible <= 0)")
    ax2.set_title("constraints")
    if result.spec.constraints:
        ax2.legend()
    for v in result.problem.variables:
        vals = np.array([r["values"][v.name] for r in h])
        if v.scale == "log":
            frac = (np.log(vals) - np.log(v.low)) / (np.log(v.high) - np.log(v.low))
        else:
            frac = (vals - v.low) / (v.high - v.low)
        ax3.plot(it, frac, label=v.name)
    ax3.set_ylim(-0.02, 1.02)
    ax3.set_xlabel("iteration")
    ax3.set_ylabel("position within bounds [1] (0 = low, 1 = high)")
    ax3.set_title("design variables")
    ax3.legend(fontsize=8)
    for ax in (ax1, ax2, ax3):
        ax.axvline(result.best_iteration, color="0.5", ls=":", lw=1)
    rounds = result.rounds_run
    fig.suptitle(f"design history ({result.status}; {result.iterations_run} iterations"
                 + (f" in {rounds} rounds" if rounds > 1 else "")
                 + f"; dotted: the returned iterate, {result.best_iteration})")
    return _save(fig, path)


def _virgin_curve(vehicle, x):
    from .._laws import honeycomb

    hc = vehicle.honeycomb.curve()
    return np.asarray([float(honeycomb(jnp.asarray(xi), jnp.asarray(xi), hc).force) for xi in x])


def _force_stroke(result, path: Path) -> Path:
    fig = _figure(figsize=(7.5, 4.5))
    ax = fig.subplots()
    margin = next((c.threshold for c in result.spec.constraints if c.name == "stroke"), None)
    for veh, name, col in ((result.baseline, "before (baseline)", "C0"),
                           (result.vehicle, "after (design)", "C3")):
        x4 = float(veh.honeycomb.x_L4)
        x = np.linspace(0.0, 1.04 * x4, 500)
        ax.plot(x * 1e3, _virgin_curve(veh, x) * 1e-3, color=col, label=name)
        ax.axvline(x4 * 1e3, color=col, ls=":", lw=1)
        if margin is not None:
            ax.axvline((x4 - margin) * 1e3, color=col, ls="--", lw=0.8)
    ver = result.verification or {}
    for tag, col in (("before", "C0"), ("after", "C3")):
        env = ver.get(tag, {}).get("max_stroke_m")
        if env:
            ax.axvspan(env["p01"] * 1e3, env["max"] * 1e3, color=col, alpha=0.12)
    f_top = max(float(result.baseline.honeycomb.F2), float(result.vehicle.honeycomb.F2))
    ax.set_ylim(0, 1.6 * f_top * 1e-3)  # the plateaus, not the bottoming-out spike
    ax.set_xlabel("buffer stroke [mm]")
    ax.set_ylabel("honeycomb force (virgin loading) [kN]")
    ax.set_title("force-stroke before/after; dotted: x_L4, dashed: x_L4 - margin;\n"
                 "shaded: verification max strokes (p01 to max)")
    ax.legend()
    return _save(fig, path)


def _outcomes(result, path: Path) -> Path:
    b, a = result.mc_before, result.mc_after
    rows = [("peak body acceleration", lambda o: o["peak_body_accel_mps2"], 1.0, "m/s^2"),
            ("max stroke, any leg", lambda o: o["max_stroke_m"].max(axis=1), 1e3, "mm"),
            ("foot slip, any leg", lambda o: o["slip_distance_m"].max(axis=1), 1e3, "mm")]
    if "min_stability_margin_m" in b.outputs:
        rows.append(("min stability margin", lambda o: o["min_stability_margin_m"], 1.0, "m"))
    fig = _figure(figsize=(4.2 * len(rows), 3.8))
    for ax, (label, fn, scale, unit) in zip(fig.subplots(1, len(rows)), rows):
        xb = np.asarray(fn(b.outputs), float)[b.failure == 0] * scale
        xa = np.asarray(fn(a.outputs), float)[a.failure == 0] * scale
        bins = np.histogram_bin_edges(np.concatenate([xb, xa]), bins=40)
        ax.hist(xb, bins=bins, color="C0", alpha=0.6, label="before")
        ax.hist(xa, bins=bins, color="C3", alpha=0.6, label="after")
        ax.set_xlabel(f"{label} [{unit}]")
        ax.set_ylabel("landings")
        ax.legend()
    v = result.verification
    tb, ta = v["before"]["tip_over"], v["after"]["tip_over"]
    tip = ("tip-over not modelled (quarter model)" if ta.get("modelled") is False else
           f"P(tip-over) before {probability_text(tb)}, after {probability_text(ta)}")
    fig.suptitle(f"verification Monte Carlo, fresh samples (n = {v['n']}, seed {v['seed']}): "
                 + tip)
    return _save(fig, path)
