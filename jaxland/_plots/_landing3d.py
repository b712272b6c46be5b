"""Figures of one landing of the full 3-D vehicle (four legs, rigid body with attitude).

``plot_landing_3d(trajectory, outcomes, out_dir, vehicle=..., scene=...)`` writes five PNGs
(attitude, legs, body, energy, and a side/front picture of the vehicle at three instants) and
returns their paths. It follows ``jaxland._plots``: matplotlib is imported only inside the
functions and only through its object-oriented API, impacts are shaded on time plots, every
axis label carries its unit, missing columns raise ``ValueError`` before anything is written,
and each PNG is written atomically (the helpers are shared with that module).
"""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from .._models._full import ground_frame, leg_geometry, quat_from_euler, quat_to_matrix
from ._landing import (
    DISSIPATION,
    ELASTIC,
    KN,
    MM,
    SHADE,
    _columns,
    _fig16,
    _grid,
    _Landing,
    _render,
    _style,
    _time_panel,
)

__all__ = ["plot_landing_3d", "REQUIRED_COLUMNS_3D", "PER_LEG_COLUMNS"]

PER_LEG_COLUMNS = (
    "stroke_m", "strut_force_N", "aux_force_N", "normal_force_N", "tangential_force_N",
    "slip_indicator", "foot_x_m", "foot_y_m", "foot_z_m",
)
SCALAR_COLUMNS = (
    "time_s", "body_x_m", "body_y_m", "body_z_m", "body_vx_mps", "body_vy_mps", "body_vz_mps",
    "body_ax_mps2", "body_ay_mps2", "body_az_mps2", "roll_deg", "pitch_deg", "yaw_deg",
    "tilt_deg", "omega_x_radps", "omega_y_radps", "omega_z_radps", "stability_margin_m",
    "kinetic_J", "potential_J", *ELASTIC, *DISSIPATION, "energy_residual_J",
)
REQUIRED_COLUMNS_3D = SCALAR_COLUMNS + PER_LEG_COLUMNS

BODY_RADIUS_M = 0.6  # the body drawn as a cylinder of this radius ...
BODY_Z_M = (-0.5, 2.7)  # ... between these body-frame heights (centre of mass at 0)
STATES = (  # slip indicator value -> (name, colour)
    (1.0, "slip", "tab:red"), (0.0, "stick", "0.35"), (0.5, "in the air", "0.88"))
GROUND = dict(color="saddlebrown")


def plot_landing_3d(trajectory: dict, outcomes: dict, out_dir, *, vehicle, scene) -> list[Path]:
    """Write the 3-D landing figures as PNGs in ``out_dir`` (created if needed); return their
    paths: ``fig3d_attitude.png``, ``fig3d_legs.png``, ``fig3d_body.png``, ``fig3d_energy.png``,
    ``fig3d_views.png``.

    ``trajectory`` maps column names (units in the names) to arrays: 1-D per sample, or
    (n_samples, n_legs) for the per-leg quantities (``PER_LEG_COLUMNS``); ``outcomes`` is
    ``Landing.outcomes`` (``impacts`` are shaded; ``touchdown_time_s`` picks the first view).
    ``vehicle`` (a ``jaxland.Vehicle``) gives the leg geometry drawn, ``scene`` (a
    ``jaxland.Scene``) the ground plane. Raises ``ValueError`` naming any missing or malformed
    column before anything is written.
    """
    lnd = _validate(trajectory, outcomes, vehicle.n_legs)
    views = _instants(lnd, outcomes)
    geom = dict(_geometry(vehicle, scene, lnd, [i for i, _ in views]), views=views)
    return _render(_FIGURES, out_dir, lnd, outcomes, geom)


def _validate(trajectory, outcomes, n_legs) -> _Landing:
    d, t = _columns(trajectory, REQUIRED_COLUMNS_3D)
    bad = [c for c in SCALAR_COLUMNS if d[c].shape != t.shape]
    bad += [c for c in PER_LEG_COLUMNS if d[c].shape != (t.size, n_legs)]
    if bad:
        raise ValueError(f"column(s) {', '.join(bad)} do not have the shape {t.shape} of time_s "
                         f"(per-leg columns: ({t.size}, {n_legs}), one column per leg)")
    impacts = [(float(i["start_s"]), float(t[-1] if i["end_s"] is None else i["end_s"]))
               for i in outcomes.get("impacts") or []]
    e0 = outcomes.get("energy_initial_J")
    if e0 is None:
        e0 = d["kinetic_J"][0] + d["potential_J"][0] + sum(d[c][0] for c in ELASTIC)
    return _Landing(d, t, impacts, float("nan"), float(e0), {})


def _geometry(vehicle, scene, lnd, samples) -> dict:
    """Body-frame leg joints ``P``, ``A_plus``, ``A_minus`` (n, 3) [m], the ground ``normal``
    (3,) and the body-to-world rotation ``R`` (k, 3, 3) at each of ``samples`` (from the roll,
    pitch and yaw columns), as numpy arrays: one compiled call, not dozens of eager JAX ops."""
    rpy = np.deg2rad([lnd.d[c][samples] for c in ("roll_deg", "pitch_deg", "yaw_deg")])
    P, A_plus, A_minus, normal, R = _geometry_jax(vehicle, scene, rpy)
    return dict(P=np.asarray(P), A_plus=np.asarray(A_plus), A_minus=np.asarray(A_minus),
                normal=np.asarray(normal), R=np.asarray(R))


@eqx.filter_jit
def _geometry_jax(vehicle, scene, rpy):
    P, A_plus, A_minus, _ = leg_geometry(vehicle)
    R = jax.vmap(lambda r, p, y: quat_to_matrix(quat_from_euler(r, p, y)))(*rpy)
    return P, A_plus, A_minus, ground_frame(scene)[0], R


def _legs_panel(ax, lnd, title, ylabel, y, xlabel=True):
    """One line per leg (colour ``Ci`` for leg i), impacts shaded, no legend (the figure has)."""
    _time_panel(ax, lnd, title, ylabel, [(f"leg {i}", y[:, i]) for i in range(y.shape[1])],
                xlabel=xlabel)
    if ax.get_legend() is not None:
        ax.get_legend().remove()


def _shade(ax, lnd):
    for start, end in lnd.impacts:
        ax.axvspan(start, end, **SHADE)


# ---------------------------------------------------------------------------------------------
# Figures


def _fig_attitude(fig, lnd, outcomes, geom):
    d = lnd.d
    ax = _grid(fig, 2, 2, "3-D landing: attitude and stability")
    _time_panel(ax[0], lnd, "(a) roll, pitch and tilt (angle of the body axis from vertical)",
                "angle [deg]", [(c.removesuffix("_deg"), d[c])
                                for c in ("roll_deg", "pitch_deg", "tilt_deg")], xlabel=False)
    _time_panel(ax[1], lnd, "(b) yaw (heading of leg 0)", "angle [deg]",
                [("yaw", d["yaw_deg"])], xlabel=False)
    _time_panel(ax[2], lnd, "(c) body angular rates (body frame)", "rate [rad/s]",
                [(f"ω_{a}", d[f"omega_{a}_radps"]) for a in "xyz"])
    m = d["stability_margin_m"]
    i = int(np.argmin(m))
    _time_panel(ax[3], lnd, f"(d) stability margin (min {m[i]:.3g} m at {lnd.t[i]:.3g} s)",
                "margin [m]", [("margin", m)])
    ax[3].axhline(0.0, color="k", lw=0.8)
    ax[3].fill_between(lnd.t, m, 0.0, where=m < 0, color="tab:red", alpha=0.3, lw=0,
                       label="tipping")
    ax[3].plot(lnd.t[i], m[i], "v", color="tab:red", ms=5)
    ax[3].annotate("below 0: centre of mass outside the feet's polygon (tipping)",
                   (0.01, 0.03), xycoords="axes fraction", fontsize="small", color="0.3")
    low, high = ax[3].get_ylim()
    pad = 0.1 * (high - low)
    ax[3].set_ylim(min(low, -pad), max(high, pad))  # keep the zero line in view


def _fig_legs(fig, lnd, outcomes, geom):
    d = lnd.d
    n = d["stroke_m"].shape[1]
    fig.suptitle("3-D landing: legs  (shaded: impacts)", fontsize="large")
    ax = fig.subplots(3, 2, sharex=True).ravel()
    _legs_panel(ax[0], lnd, "(a) buffer stroke (+ compression)", "stroke [mm]",
                d["stroke_m"] * MM, xlabel=False)
    _legs_panel(ax[1], lnd, "(b) main strut force (+ compression)", "force [kN]",
                d["strut_force_N"] * KN, xlabel=False)
    _legs_panel(ax[2], lnd, "(c) ground normal force on foot", "force [kN]",
                d["normal_force_N"] * KN, xlabel=False)
    _legs_panel(ax[3], lnd, "(d) ground tangential force on foot (magnitude)", "force [kN]",
                d["tangential_force_N"] * KN, xlabel=False)
    _legs_panel(ax[4], lnd, "(e) auxiliary struts, sum of the pair (+ compression)", "force [kN]",
                d["aux_force_N"] * KN)
    _slip_states(ax[5], lnd, d["slip_indicator"])
    fig.legend(*ax[0].get_legend_handles_labels(), loc="outside lower center", ncols=n,
               fontsize="medium", frameon=False)


def _slip_states(ax, lnd, slip):
    """Contact state per leg as coloured bars (one row per leg, leg 0 on top)."""
    from matplotlib.patches import Patch

    t, n = lnd.t, slip.shape[1]
    edges = np.append(t, t[-1] + (t[-1] - t[-2]))  # sample i holds over [t_i, t_i+1)
    code = np.argmin(np.abs(slip[:, :, None] - np.array([v for v, _, _ in STATES])), axis=-1)
    for leg in range(n):
        c = code[:, leg]
        starts = np.flatnonzero(np.diff(c, prepend=-1))
        stops = np.append(starts[1:], c.size)
        for k, (_, _, colour) in enumerate(STATES):
            sel = c[starts] == k
            spans = np.column_stack([edges[starts[sel]], edges[stops[sel]] - edges[starts[sel]]])
            ax.broken_barh(spans, (leg - 0.4, 0.8), color=colour, lw=0)
    _shade(ax, lnd)
    ax.set(ylim=(n + 0.4, -0.5), yticks=range(n))  # room for the legend below the bars
    ax.set_yticklabels([f"leg {i}" for i in range(n)])
    for i, label in enumerate(ax.get_yticklabels()):
        label.set_color(f"C{i}")
    _style(ax, "(f) foot contact state (slip indicator)", "time [s]", "leg [-]")
    ax.grid(False)
    ax.legend(handles=[Patch(color=col, label=name) for _, name, col in STATES],
              fontsize="small", loc="lower center", ncols=3, frameon=False)


def _fig_body(fig, lnd, outcomes, geom):
    d = lnd.d
    fig.suptitle("3-D landing: main body  (shaded: impacts)", fontsize="large")
    ax = fig.subplot_mosaic([["p", "top"], ["v", "top"], ["a", "top"]], width_ratios=[1.3, 1])
    for k in ("v", "a"):
        ax[k].sharex(ax["p"])
    _time_panel(ax["p"], lnd, "(a) centre-of-mass position (world)", "position [m]",
                [(a, d[f"body_{a}_m"]) for a in "xyz"], xlabel=False)
    _time_panel(ax["v"], lnd, "(b) velocity", "velocity [m/s]",
                [(f"v_{a}", d[f"body_v{a}_mps"]) for a in "xyz"], xlabel=False)
    _time_panel(ax["a"], lnd, "(c) acceleration", "acceleration [m/s²]",
                [(f"a_{a}", d[f"body_a{a}_mps2"]) for a in "xyz"])
    _top_view(ax["top"], lnd, geom)


def _top_view(ax, lnd, geom):
    d = lnd.d
    fx, fy = d["foot_x_m"], d["foot_y_m"]
    n = fx.shape[1]
    ax.plot(d["body_x_m"], d["body_y_m"], color="k", lw=1.5, label="body (centre of mass)")
    ax.plot(d["body_x_m"][0], d["body_y_m"][0], "o", color="k", ms=5)
    ax.plot(d["body_x_m"][-1], d["body_y_m"][-1], "s", color="k", ms=5)
    for i in range(n):
        ax.plot(fx[:, i], fy[:, i], color=f"C{i}", lw=1.2, label=f"foot {i}")
        ax.plot(fx[0, i], fy[0, i], "o", color=f"C{i}", ms=4)
        ax.plot(fx[-1, i], fy[-1, i], "s", color=f"C{i}", ms=4)
    for j, ls, label in ((0, ":", "feet at start"), (-1, "--", "feet at end")):
        ax.fill(fx[j], fy[j], fill=False, ls=ls, lw=0.8, ec="0.5", label=label)
    ax.plot([], [], "o", color="0.3", ms=4, label="start")
    ax.plot([], [], "s", color="0.3", ms=4, label="end")
    n_g = geom["normal"]
    if np.hypot(n_g[0], n_g[1]) > 1e-9:  # the normal leans downhill
        down = n_g[:2] / np.hypot(n_g[0], n_g[1])
        slope = np.degrees(np.arccos(np.clip(n_g[2], -1.0, 1.0)))
        tail = np.array([0.85, 0.12])
        ax.annotate(f"downhill ({slope:.2g}° slope)", xy=tail + 0.1 * down, xytext=tail,
                    xycoords="axes fraction", ha="center", va="center",
                    fontsize="small", arrowprops=dict(arrowstyle="-|>", color=GROUND["color"]),
                    color=GROUND["color"])
    ax.set_aspect("equal", adjustable="datalim")
    _style(ax, "(d) top view: body and feet tracks", "x [m]", "y [m]")
    ax.legend(fontsize="small", loc="upper left", ncols=2, framealpha=0.9)


def _fig_energy(fig, lnd, outcomes, geom):
    _fig16(fig, lnd)
    fig.suptitle("3-D landing: energy (all legs and the body)  (shaded: impacts)",
                 fontsize="large")


# ---------------------------------------------------------------------------------------------
# Pictures of the vehicle


def _instants(lnd, outcomes) -> list[tuple[int, str]]:
    """Touchdown (the first sample if none), the maximum total stroke of all legs, and the end.
    (The crushed honeycomb keeps its stroke, so after a rocking landing the maximum can come
    late, close to the end.)"""
    t, stroke = lnd.t, lnd.d["stroke_m"]
    t_td = outcomes.get("touchdown_time_s")
    i_td = 0 if t_td is None else min(int(np.searchsorted(t, t_td)), t.size - 1)
    i_mid = int(np.argmax(stroke.sum(axis=1)))
    return [(i_td, "touchdown" if t_td is not None else "start"), (i_mid, "maximum stroke"),
            (t.size - 1, "end")]


def _pose(lnd, geom, k) -> dict:
    """World coordinates (n, 3) [m] of the legs' joints and feet, the body axis ends and the
    centre of mass at the ``k``-th view instant."""
    d = lnd.d
    i, R = geom["views"][k][0], geom["R"][k]
    p = np.array([d["body_x_m"][i], d["body_y_m"][i], d["body_z_m"][i]])
    feet = np.column_stack([d[f"foot_{a}_m"][i] for a in "xyz"])
    axis = np.array([[0.0, 0.0, z] for z in BODY_Z_M])
    world = {k: p + geom[k] @ R.T for k in ("P", "A_plus", "A_minus")}
    return dict(**world, feet=feet, axis=p + axis @ R.T, com=p)


def _fig_views(fig, lnd, outcomes, geom):
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    instants = geom["views"]
    poses = [_pose(lnd, geom, k) for k in range(len(instants))]
    views = (("side view", 0, 2, 1, +1), ("front view", 1, 2, 0, -1))  # h, v, depth axis, sign
    top = lnd.d["stroke_m"].sum(axis=1).max() * MM
    fig.suptitle("3-D landing: the vehicle in orthographic views (world frame) at touchdown, "
                 f"maximum total stroke of all legs ({top:.0f} mm) and end", fontsize="large")
    ax = fig.subplots(2, len(instants), squeeze=False)
    for row, (view, h, v, depth, sign) in enumerate(views):
        lims = _view_limits(poses, h, v, geom, depth)
        for col, ((i, what), pose) in enumerate(zip(instants, poses, strict=True)):
            a = ax[row, col]
            _draw_ground(a, lnd, geom, i, pose, h, v, depth, lims)
            _draw_vehicle(a, pose, h, v, depth, sign)
            a.set(xlim=lims[0], ylim=lims[1])
            a.set_aspect("equal", adjustable="box")
            a.grid(alpha=0.3)
            tilt, total = lnd.d["tilt_deg"][i], lnd.d["stroke_m"][i].sum() * MM
            _style(a, f"{view}: {what}\nt = {lnd.t[i]:.3f} s, tilt {tilt:.1f}°, "
                   f"total stroke {total:.0f} mm", f"{'xyz'[h]} [m]", f"{'xyz'[v]} [m]")
    looks = "side view: looking along +y (leg at −y in front); " \
            "front view: looking along −x (leg at +x in front)"
    handles = [Patch(fc="0.85", ec="k", label="body (cylinder outline)"),
               Line2D([], [], color="0.3", lw=2.5, label="main strut (joint P → foot)"),
               Line2D([], [], color="0.3", lw=0.9, label="auxiliary struts (A± → foot)"),
               Line2D([], [], color="0.3", lw=0.8, ls=":", label="body structure P–A"),
               Line2D([], [], color="0.3", marker="o", ls="", label="foot"),
               Line2D([], [], color="k", marker="+", ls="", ms=8, label="centre of mass"),
               Line2D([], [], lw=1.2, label="ground, section through the centre of mass",
                      **GROUND),
               Patch(fc=GROUND["color"], alpha=0.25, label="ground under the feet (depth range)")]
    handles += [Line2D([], [], color=f"C{k}", lw=2.5, label=f"leg {k}")
                for k in range(len(geom["P"]))]
    fig.legend(handles=handles, loc="outside lower center", ncols=7, fontsize="small",
               frameon=False, title=looks, title_fontsize="small")


def _view_limits(poses, h, v, geom, depth):
    pts = np.concatenate([np.concatenate([p["feet"], p["axis"], p["A_plus"], p["A_minus"]])
                          for p in poses])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    lo[[h, depth]] -= BODY_RADIUS_M
    hi[[h, depth]] += BODY_RADIUS_M
    span = max(hi[h] - lo[h], hi[v] - lo[v])
    pad = 0.05 * span
    z_ground = min(_ground_z(geom["normal"], h, depth, np.array([lo[h], hi[h]]), lo[depth]).min(),
                   _ground_z(geom["normal"], h, depth, np.array([lo[h], hi[h]]), hi[depth]).min())
    return ((lo[h] - pad, hi[h] + pad), (min(lo[v], z_ground) - 1.5 * pad, hi[v] + pad))


def _ground_z(n_g, h, depth, x, y_depth):
    """Height [m] of the ground plane (through the origin, normal ``n_g``) at view abscissa
    ``x`` (world axis ``h``) and depth coordinate ``y_depth`` (world axis ``depth``)."""
    return -(n_g[h] * x + n_g[depth] * y_depth) / n_g[2]


def _draw_ground(ax, lnd, geom, i, pose, h, v, depth, lims):
    x = np.linspace(*lims[0], 50)
    n_g = geom["normal"]
    z_c = _ground_z(n_g, h, depth, x, pose["com"][depth])
    dmin, dmax = pose["feet"][:, depth].min(), pose["feet"][:, depth].max()
    z1, z2 = _ground_z(n_g, h, depth, x, dmin), _ground_z(n_g, h, depth, x, dmax)
    ax.fill_between(x, np.minimum(z1, z2), np.maximum(z1, z2), alpha=0.25, lw=0,
                    color=GROUND["color"], zorder=1)
    ax.fill_between(x, np.minimum(z1, z2), lims[1][0], alpha=0.08, lw=0,
                    color=GROUND["color"], zorder=0)
    ax.plot(x, z_c, lw=1.2, zorder=1.5, **GROUND)


def _draw_vehicle(ax, pose, h, v, depth, sign):
    """Body outline (side rectangle of the cylinder), struts and feet in the (h, v) plane;
    legs nearer the viewer (``sign`` * depth smaller) drawn on top of the body, others behind."""
    a, b = pose["axis"][:, [h, v]]
    u = (b - a) / np.hypot(*(b - a))
    w = BODY_RADIUS_M * np.array([-u[1], u[0]])
    ax.fill(*np.array([a + w, b + w, b - w, a - w]).T, fc="0.85", ec="k", lw=1.0, zorder=3)
    ax.plot(*np.array([a, b]).T, color="0.5", lw=0.6, ls="-.", zorder=3.1)
    ax.plot(*pose["com"][[h, v]], "+", color="k", ms=9, mew=1.5, zorder=3.2)
    com_depth = pose["com"][depth]
    for k, foot in enumerate(pose["feet"]):
        z = 2.5 if sign * (foot[depth] - com_depth) > 0.1 * BODY_RADIUS_M else 4.0
        P, Ap, Am = (pose[c][k] for c in ("P", "A_plus", "A_minus"))
        kw = dict(color=f"C{k}", zorder=z, solid_capstyle="round")
        ax.plot([P[h], foot[h]], [P[v], foot[v]], lw=2.5, **kw)
        for A in (Ap, Am):
            ax.plot([A[h], foot[h]], [A[v], foot[v]], lw=0.9, **kw)
            ax.plot([P[h], A[h]], [P[v], A[v]], lw=0.8, ls=":", color="0.3", zorder=z)
        ax.plot(foot[h], foot[v], "o", ms=5, mec="k", mew=0.5, **kw)


_FIGURES = (
    ("fig3d_attitude.png", (12, 7.5), _fig_attitude),
    ("fig3d_legs.png", (12, 9.5), _fig_legs),
    ("fig3d_body.png", (14, 8), _fig_body),
    ("fig3d_energy.png", (13, 10), _fig_energy),
    ("fig3d_views.png", (14, 12.5), _fig_views),
)
