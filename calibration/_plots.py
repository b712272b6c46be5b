"""Figures of a fit and of a prediction check (matplotlib object-oriented API, no pyplot)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._data import LEG_COLUMN, base_channel
from ._report import atomic_savefig

__all__ = ["plot_fit", "plot_prediction"]

_LABEL = {"normal_force_N": ("normal force [kN]", 1e-3),
          "buffer_force_N": ("buffer (strut) force [kN]", 1e-3),
          "stroke_m": ("stroke [mm]", 1e3),
          "body_accel_mps2": ("body acceleration [m/s^2]", 1.0)}


def _label(col: str) -> tuple[str, float]:
    """Axis label and scale of a data column (a leg's column names its leg)."""
    label, scale = _LABEL[base_channel(col)]
    m = LEG_COLUMN.match(col)
    return (f"leg {m.group(1)}: {label}" if m else label), scale


def _figure(**kw):
    from matplotlib.figure import Figure

    return Figure(layout="constrained", **kw)


def plot_fit(result, out_dir: Path) -> list[Path]:
    """``fit_<drop>.png`` (data vs fit and residuals per channel, over the final window) for each
    drop, and ``fit_history.png`` (loss and parameter histories, correlations)."""
    paths = []
    window_ms = result.problem.active_window_s * 1e3
    for tr in result.traces():
        chans = list(tr["data"])
        fig = _figure(figsize=(11, 2.3 * len(chans) + 0.6))
        axs = np.atleast_2d(fig.subplots(len(chans), 2, sharex=True, squeeze=False))
        for j, c in enumerate(chans):
            t_ms = tr["time_s"][c] * 1e3
            label, scale = _label(c)
            ax, axr = axs[j]
            ax.plot(t_ms, tr["data"][c] * scale, ".", ms=2, color="0.5", label="data")
            ax.plot(t_ms, tr["model"][c] * scale, "-", lw=1.2, color="C3", label="fit")
            ax.set_ylabel(label)
            axr.plot(t_ms, (tr["data"][c] - tr["model"][c]) * scale, ".", ms=2, color="C0")
            sig = tr["noise_std"][c] * scale
            axr.axhspan(-2 * sig, 2 * sig, color="C2", alpha=0.2, label="+/-2 noise std")
            axr.set_ylabel(f"residual {label.split(' [')[0]} [{label.split('[')[1]}")
            ax.grid(alpha=0.3)
            axr.grid(alpha=0.3)
            if j == 0:
                ax.legend(loc="lower right")
                axr.legend(loc="lower right")
        for ax in axs[-1]:
            ax.set_xlabel("time after fitted touchdown [ms]")
        fig.suptitle(f"{tr['name']}: data vs fit ({window_ms:g} ms window)"
                     + (" - SYNTHETIC data" if tr["synthetic"] else ""))
        paths.append(atomic_savefig(fig, out_dir / f"fit_{tr['name']}.png"))
    paths.append(_plot_history(result, out_dir / "fit_history.png"))
    return paths


def _plot_history(result, path: Path) -> Path:
    fig = _figure(figsize=(14, 4.2))
    ax1, ax2, ax3 = fig.subplots(1, 3)
    h = result.history
    it = np.arange(1, len(h) + 1)
    ax1.semilogy(it, [x["loss"] for x in h], "o-", ms=3)
    stage_ends = np.cumsum([s["iterations"] for s in result.stages])
    for e, s in zip(stage_ends, result.stages):
        ax1.axvline(e + 0.5, color="0.7", ls=":")
        ax2.axvline(e + 0.5, color="0.7", ls=":")
    ax1.set_xlabel("iteration (all stages)")
    ax1.set_ylabel("loss 0.5 sum((r / noise std)^2) [1]")
    ax1.set_title("loss (dotted: window grows)")
    vals = np.array([x["values"] for x in h]) if h else np.zeros((0, len(result.names)))
    for k, n in enumerate(result.names):
        if len(vals):
            ax2.plot(it, vals[:, k] / result.values[k], label=n)
    ax2.set_xlabel("iteration (all stages)")
    ax2.set_ylabel("value / fitted value [1]")
    ax2.set_title("parameter histories")
    ax2.legend()
    corr = np.nan_to_num(result.correlation)
    im = ax3.imshow(corr, vmin=-1, vmax=1, cmap="RdBu_r")
    ax3.set_xticks(range(len(result.names)), result.names, rotation=45)
    ax3.set_yticks(range(len(result.names)), result.names)
    for a in range(len(result.names)):
        for b in range(len(result.names)):
            ax3.text(b, a, f"{corr[a, b]:.2f}", ha="center", va="center", fontsize=7)
    fig.colorbar(im, ax=ax3, label="correlation [1]")
    ax3.set_title("parameter correlation")
    return atomic_savefig(fig, path)


def plot_prediction(pred, path: Path) -> Path:
    """Data vs prediction over the whole record, per channel, with the compared metrics."""
    d = pred.drop
    data = d.corrected
    chans = list(data)
    lines = [f"{k}: data {v['data']:.5g}, model {v['model']:.5g}, error {v['rel_error']:+.2%}"
             for k, v in pred.metrics.items()]
    # the metrics get a panel of their own below the traces: a record of several legs'
    # channels has more lines than the first axes holds beside its legend
    text_h = 0.14 * len(lines) + 0.3  # inches, at 7 pt
    fig = _figure(figsize=(11, 2.3 * len(chans) + 0.8 + text_h))
    grid = fig.add_gridspec(len(chans) + 1, 1, height_ratios=[2.3] * len(chans) + [text_h])
    axs = [fig.add_subplot(grid[0, 0])]
    axs += [fig.add_subplot(grid[i, 0], sharex=axs[0]) for i in range(1, len(chans))]
    t_rel = d.time_s - pred.touchdown_time_s
    for ax, c in zip(axs, chans):
        label, scale = _label(c)
        ax.plot(t_rel * 1e3, data[c] * scale, ".", ms=1.5, color="0.5", label="data")
        keep = pred.model_time_s <= t_rel[-1]
        ax.plot(pred.model_time_s[keep] * 1e3, pred.model[base_channel(c)][keep] * scale, "-", lw=1,
                color="C3", label="prediction")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    for ax in axs[:-1]:
        ax.tick_params(labelbottom=False)
    axs[-1].set_xlabel("time after touchdown [ms]")
    box = fig.add_subplot(grid[-1, 0])
    box.axis("off")
    box.text(0.0, 1.0, "\n".join(lines), transform=box.transAxes, ha="left", va="top",
             fontsize=7, family="monospace")
    axs[0].legend(loc="upper right")
    fig.suptitle(f"prediction of {d.name}" + (" (SYNTHETIC data)" if d.synthetic else ""))
    return atomic_savefig(fig, path)
