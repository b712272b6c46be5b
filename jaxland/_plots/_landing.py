"""Figures of one landing, after the paper's Figs 9-16 (section 3.1).

``plot_landing(trajectory, outcomes, out_dir)`` writes one PNG per paper figure and returns the
paths. matplotlib is imported only inside the functions here (importing jaxland never pulls it
in) and only through its object-oriented API (``Figure``, never pyplot), so plotting works
headless and leaves no global figure state behind. Each PNG is written atomically.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._files import atomic_savefig

__all__ = ["plot_landing", "REQUIRED_COLUMNS"]

DPI = 120
ELASTIC = ("elastic_honeycomb_J", "elastic_aux_J", "elastic_ground_J", "elastic_tangential_J")
DISSIPATION = ("diss_crush_J", "diss_struct_damping_J", "diss_slip_J", "diss_ground_plastic_J",
               "diss_ground_damping_J")
REQUIRED_COLUMNS = (
    "time_s", "body_z_m", "body_vz_mps", "body_az_mps2",
    "foot_r_m", "foot_z_m", "foot_vr_mps", "foot_vz_mps", "foot_ar_mps2", "foot_az_mps2",
    "stroke_m", "stroke_max_m", "plastic_set_m", "buffer_velocity_mps",
    "honeycomb_force_N", "damping_force_N", "strut_force_N", "aux_force_N",
    "normal_force_N", "tangential_force_N", "pit_depth_m", "slip_indicator",
    "kinetic_J", "potential_J", *ELASTIC, *DISSIPATION, "energy_residual_J",
)
SHADE = dict(color="tab:orange", alpha=0.12, lw=0, zorder=0)
MM, KN = 1e3, 1e-3


@dataclass(frozen=True)
class _Landing:
    """Validated columns (float arrays) plus what several figures share."""

    d: dict
    t: np.ndarray
    impacts: list  # [(start_s, end_s)], an open end clipped to the last sample
    r_td: float  # radial foot position at touchdown [m], the tangential reference
    e0: float  # initial energy [J]
    breakpoints: dict  # name -> stroke [m]


def plot_landing(trajectory: dict, outcomes: dict, out_dir, *,
                 breakpoints_m: dict | None = None) -> list[Path]:
    """Write the paper's Figs 9, 10 and 12-16 (Fig. 11, the foot phase portraits, is not drawn)
    for one landing as PNGs in ``out_dir`` (created if needed); return their paths in order.

    ``trajectory`` maps column names (units in the names, as ``Landing.trajectory``) to 1-D
    arrays; ``outcomes`` is ``Landing.outcomes`` (``impacts`` intervals are shaded on time plots).
    ``breakpoints_m`` (e.g. ``{"x_L1": ..., "x_L4": ...}`` in metres) adds the honeycomb stage
    limits to the stroke plot. Raises ``ValueError`` naming any missing or malformed column
    before anything is written.
    """
    lnd = _validate(trajectory, outcomes, breakpoints_m)
    return _render(_FIGURES, out_dir, lnd)


def _render(figures, out_dir, *args) -> list[Path]:
    """Draw each (file name, size, draw(fig, *args)) into its own PNG in ``out_dir``."""
    from matplotlib.figure import Figure

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, size, draw in figures:
        fig = Figure(figsize=size, layout="constrained")
        draw(fig, *args)
        paths.append(_save(fig, out_dir / name))
    return paths


def _columns(trajectory, required):
    """The required columns as float arrays, and the time axis, checked (names the column)."""
    missing = [c for c in required if c not in trajectory]
    if missing:
        raise ValueError(f"trajectory is missing column(s): {', '.join(missing)}")
    d = {c: np.asarray(trajectory[c], dtype=float) for c in required}
    t = d["time_s"]
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"column 'time_s' must be 1-D with at least 2 samples, got {t.shape}")
    return d, t


def _validate(trajectory, outcomes, breakpoints_m) -> _Landing:
    d, t = _columns(trajectory, REQUIRED_COLUMNS)
    bad = [c for c, v in d.items() if v.shape != t.shape]
    if bad:
        raise ValueError(f"column(s) {', '.join(bad)} do not have the shape {t.shape} of time_s")
    impacts = []
    for imp in outcomes.get("impacts") or []:
        start, end = imp["start_s"], imp["end_s"]
        impacts.append((float(start), float(t[-1] if end is None else end)))
    t_td = outcomes.get("touchdown_time_s")
    t_td = impacts[0][0] if t_td is None and impacts else t_td
    r_td = float(np.interp(t_td, t, d["foot_r_m"]) if t_td is not None else d["foot_r_m"][0])
    e0 = outcomes.get("energy_initial_J")
    if e0 is None:
        e0 = d["kinetic_J"][0] + d["potential_J"][0] + sum(d[c][0] for c in ELASTIC)
    bps = {k: float(v) for k, v in (breakpoints_m or {}).items()}
    return _Landing(d, t, impacts, r_td, float(e0), bps)


def _save(fig, path: Path) -> Path:
    return atomic_savefig(fig, path, dpi=DPI)


# ---------------------------------------------------------------------------------------------
# Shared panel helpers


def _grid(fig, nrows, ncols, title, sharex=True):
    fig.suptitle(title + "  (shaded: impacts)", fontsize="large")
    return fig.subplots(nrows, ncols, sharex=sharex, squeeze=False).ravel()


def _style(ax, title, xlabel, ylabel):
    ax.set_title(title, loc="left", fontsize="medium")
    ax.set(xlabel=xlabel, ylabel=ylabel)
    ax.grid(alpha=0.3)


def _time_panel(ax, lnd, title, ylabel, curves, xlabel=True):
    """Lines ``curves = [(label, y), ...]`` against time, impacts shaded."""
    for label, y in curves:
        ax.plot(lnd.t, y, lw=1, label=label)
    for start, end in lnd.impacts:
        ax.axvspan(start, end, **SHADE)
    _style(ax, title, "time [s]" if xlabel else None, ylabel)
    if len(curves) > 1:
        ax.legend(fontsize="small", loc="best")
    return ax


def _slip_twin(ax, lnd):
    """Slip indicator (1 slip, 0 stick, 0.5 air) on a right-hand axis, legend merged."""
    tw = ax.twinx()
    tw.plot(lnd.t, lnd.d["slip_indicator"], color="0.6", lw=0.7, drawstyle="steps-post",
            label="slip indicator")
    tw.set(ylim=(-0.1, 1.1), yticks=[0, 0.5, 1], ylabel="slip indicator [-]")
    tw.set_yticklabels(["0 stick", "0.5 air", "1 slip"], fontsize="small")
    ax.set_zorder(tw.get_zorder() + 1)  # data lines above the indicator
    ax.patch.set_visible(False)
    lines = ax.get_lines() + tw.get_lines()
    ax.legend(lines, [ln.get_label() for ln in lines], fontsize="small", loc="upper right")


def _first_impact_zoom(ax, lnd):
    if lnd.impacts:
        start, end = lnd.impacts[0]
        pad = 0.05 * (end - start)
        ax.set_xlim(start - pad, end + pad)


# ---------------------------------------------------------------------------------------------
# One function per paper figure


def _fig09(fig, lnd):
    d = lnd.d
    ax = _grid(fig, 3, 1, "Paper Fig. 9: foot velocity and tangential motion pattern", False)
    _time_panel(ax[0], lnd, "(a) normal velocity", "velocity [m/s]",
                [("foot normal", d["foot_vz_mps"])])
    _time_panel(ax[1], lnd, "(b) tangential velocity and slip indicator", "velocity [m/s]",
                [("foot tangential", d["foot_vr_mps"])])
    _slip_twin(ax[1], lnd)
    _time_panel(ax[2], lnd, "(c) first impact (zoom)", "velocity [m/s]",
                [("foot normal", d["foot_vz_mps"]), ("foot tangential", d["foot_vr_mps"])])
    _slip_twin(ax[2], lnd)
    _first_impact_zoom(ax[2], lnd)


def _fig10(fig, lnd):
    from matplotlib.collections import LineCollection

    d = lnd.d
    fig.suptitle("Paper Fig. 10: foot position  (shaded: impacts)", fontsize="large")
    ax = fig.subplot_mosaic([["n", "p"], ["t", "p"]], width_ratios=[1.4, 1])
    ax["t"].sharex(ax["n"])
    z, pit, tan = d["foot_z_m"] * MM, d["pit_depth_m"] * MM, (d["foot_r_m"] - lnd.r_td) * MM
    _time_panel(ax["n"], lnd, "(a) normal position (foot height)", "position [mm]",
                [("foot", z), ("ground surface (−pit depth)", -pit)], xlabel=False)
    low = min(z.min(), -pit.max())
    if lnd.impacts and low < 0 and z.max() > -4 * low:  # zoom on the contact, not the drop
        ax["n"].set_ylim(1.3 * low, -4 * low)
        ax["n"].annotate(f"zoomed on contact: the foot starts at {z[0]:.0f} mm", (0.99, 0.97),
                         xycoords="axes fraction", ha="right", va="top", fontsize="small")
    _time_panel(ax["t"], lnd, "(b) tangential position (from touchdown)", "position [mm]",
                [("foot", tan)])
    # (c) the path from just before touchdown on, coloured by time (the drop above is a line).
    i0 = max(int(np.searchsorted(lnd.t, lnd.impacts[0][0])) - 20, 0) if lnd.impacts else 0
    xy = np.column_stack([tan[i0:], z[i0:]])
    lc = LineCollection(np.stack([xy[:-1], xy[1:]], axis=1), array=lnd.t[i0:-1],
                        cmap="viridis", lw=1.2)
    ax["p"].add_collection(lc)
    ax["p"].autoscale_view()
    ax["p"].axhline(0.0, color="0.3", lw=0.8, ls="--", label="undisturbed ground")
    ax["p"].axhline(-pit.max(), color="tab:brown", lw=0.8, ls=":", label="deepest pit (plastic)")
    fig.colorbar(lc, ax=ax["p"], label="time [s]")
    _style(ax["p"], "(c) foot path from touchdown", "tangential position [mm]",
           "normal position [mm]")
    ax["p"].legend(fontsize="small")


def _fig12(fig, lnd):
    ax = _grid(fig, 2, 1, "Paper Fig. 12: foot acceleration")
    _time_panel(ax[0], lnd, "(a) normal", "acceleration [m/s²]",
                [("foot normal", lnd.d["foot_az_mps2"])], xlabel=False)
    _time_panel(ax[1], lnd, "(b) tangential", "acceleration [m/s²]",
                [("foot tangential", lnd.d["foot_ar_mps2"])])


def _fig13(fig, lnd):
    d = lnd.d
    ax = _grid(fig, 2, 1, "Paper Fig. 13: buffer")
    _time_panel(ax[0], lnd, "(a) buffer velocity (+ compression)", "velocity [m/s]",
                [("buffer", d["buffer_velocity_mps"])], xlabel=False)
    _time_panel(ax[1], lnd, "(b) buffer stroke", "stroke [mm]",
                [("stroke", d["stroke_m"] * MM), ("max stroke", d["stroke_max_m"] * MM),
                 ("plastic set", d["plastic_set_m"] * MM)])
    _breakpoint_lines(ax[1], lnd.breakpoints, d["stroke_max_m"].max())


def _breakpoint_lines(ax, breakpoints, top):
    """Dashed lines at the honeycomb stage limits [m] drawn in mm; limits closer than 3 % of
    the scale share one label; those far above the largest stroke ``top`` [m] are listed."""
    scale = 1.15 * max(top, 1e-6)
    shown = sorted((x, k) for k, x in breakpoints.items() if x <= scale)
    off = [f"{k} = {x * MM:.2f} mm" for k, x in breakpoints.items() if x > scale]
    groups = []
    for x, k in shown:
        if groups and x - groups[-1][-1][0] < 0.03 * scale:
            groups[-1].append((x, k))
        else:
            groups.append([(x, k)])
    for i, g in enumerate(groups):
        for j, (x, _) in enumerate(g):
            ax.axhline(x * MM, color="0.4", lw=0.7, ls="--",
                       label="honeycomb breakpoints" if i == j == 0 else None)
        label = ", ".join(k for _, k in g) + " = " + ", ".join(f"{x * MM:.2f}" for x, _ in g)
        ax.annotate(label + " mm", (0.99, g[-1][0] * MM), xycoords=("axes fraction", "data"),
                    xytext=(0, 2), textcoords="offset points", ha="right", va="bottom",
                    fontsize="x-small", color="0.3")
    if off:
        ax.plot([], [], " ", label="off scale: " + ", ".join(off))
    if breakpoints:
        ax.legend(fontsize="small")


def _fig14(fig, lnd):
    d = lnd.d
    ax = _grid(fig, 2, 2, "Paper Fig. 14: main body", sharex=False)
    _time_panel(ax[0], lnd, "(a) velocity", "velocity [m/s]", [("body", d["body_vz_mps"])])
    _time_panel(ax[1], lnd, "(b) position of the centroid", "height [m]",
                [("body", d["body_z_m"])])
    ax[2].plot(d["body_z_m"], d["body_vz_mps"], lw=0.8)
    ax[2].plot(d["body_z_m"][[0, -1]], d["body_vz_mps"][[0, -1]], "o", ms=4, color="tab:red")
    ax[2].annotate("start", (d["body_z_m"][0], d["body_vz_mps"][0]), xytext=(4, 4),
                   textcoords="offset points", fontsize="small")
    ax[2].annotate("end", (d["body_z_m"][-1], d["body_vz_mps"][-1]), xytext=(4, 4),
                   textcoords="offset points", fontsize="small")
    _style(ax[2], "(c) position–velocity phase portrait", "height [m]", "velocity [m/s]")
    _time_panel(ax[3], lnd, "(d) acceleration", "acceleration [m/s²]",
                [("body", d["body_az_mps2"])])
    ax[1].sharex(ax[0])
    ax[3].sharex(ax[0])


def _fig15(fig, lnd):
    d = lnd.d
    ax = _grid(fig, 3, 1, "Paper Fig. 15: buffer, damping, ground and auxiliary-strut forces")
    _time_panel(ax[0], lnd, "(a) main strut (+ compression)", "force [kN]",
                [("honeycomb", d["honeycomb_force_N"] * KN),
                 ("structural damping", d["damping_force_N"] * KN),
                 ("strut total", d["strut_force_N"] * KN)], xlabel=False)
    _time_panel(ax[1], lnd, "(b) ground on foot", "force [kN]",
                [("normal", d["normal_force_N"] * KN),
                 ("tangential", d["tangential_force_N"] * KN)], xlabel=False)
    _time_panel(ax[2], lnd, "(c) auxiliary strut (+ compression)", "force [kN]",
                [("auxiliary", d["aux_force_N"] * KN)])


def _fig16(fig, lnd):
    d = lnd.d
    ax = _grid(fig, 3, 2, "Paper Fig. 16: energy")
    elastic = sum(d[c] for c in ELASTIC)
    mech = d["kinetic_J"] + d["potential_J"] + elastic
    diss = sum(d[c] for c in DISSIPATION)
    _time_panel(ax[0], lnd, "(a) energy balance", "energy [J]",
                [("mechanical (kin + pot + elastic)", mech), ("dissipated", diss),
                 ("mechanical + dissipated", mech + diss)], xlabel=False)
    ax[0].axhline(lnd.e0, color="k", lw=0.8, ls=":", label="initial")
    ax[0].legend(fontsize="small", loc="center right")
    _time_panel(ax[1], lnd, "(b) kinetic", "energy [J]", [("kinetic", d["kinetic_J"])],
                xlabel=False)
    _time_panel(ax[2], lnd, "(c) elastic stores", "energy [J]",
                [(c.removeprefix("elastic_").removesuffix("_J"), d[c]) for c in ELASTIC],
                xlabel=False)
    _time_panel(ax[3], lnd, "(d) potential", "potential − initial [J]",
                [("potential", d["potential_J"] - d["potential_J"][0])], xlabel=False)
    _time_panel(ax[4], lnd, "(e) dissipation channels (stacked)", "energy [J]", [])
    ax[4].stackplot(lnd.t, *(d[c] for c in DISSIPATION), alpha=0.8,
                    labels=[c.removeprefix("diss_").removesuffix("_J") for c in DISSIPATION])
    ax[4].legend(fontsize="small", loc="upper left")
    res = d["energy_residual_J"]
    _time_panel(ax[5], lnd, f"(f) ledger residual (max |r| = {np.abs(res).max():.3g} J, "
                f"{np.abs(res).max() / max(lnd.e0, 1e-12):.1e} of initial)", "residual [J]",
                [("residual", res)])


_FIGURES = (
    ("fig09_foot_velocity.png", (10, 9), _fig09),
    ("fig10_foot_position.png", (13, 5), _fig10),
    ("fig12_foot_acceleration.png", (10, 6.5), _fig12),
    ("fig13_buffer.png", (10, 6.5), _fig13),
    ("fig14_body.png", (12, 8), _fig14),
    ("fig15_forces.png", (10, 9), _fig15),
    ("fig16_energy.png", (13, 10), _fig16),
)
