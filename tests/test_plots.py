"""plot_landing: one readable PNG per paper figure, atomic writes, clear errors (no simulation)."""

import subprocess
import sys

import numpy as np
import pytest

from jaxland import QuarterModel
from jaxland._plots import plot_landing

COLUMNS = QuarterModel.COLUMNS

N = 500
BREAKPOINTS = {"x_L1": 0.47e-3, "x_L2": 57.6e-3, "x_L3": 58.23e-3, "x_L4": 183.23e-3}


def synthetic_landing():
    """Plausible curves for every trajectory column: a drop, touchdown at 0.2 s, a decaying
    bounce; outcomes with a closed and an open impact."""
    t = np.linspace(0.0, 0.5, N)
    after = np.clip(t - 0.2, 0.0, None)
    ring = np.exp(-after / 0.05) * np.sin(2 * np.pi * 12 * after)
    contact = t >= 0.2
    traj = {c: 0.1 * ring + 0.01 * np.cos(7 * t) for c in COLUMNS}
    traj.update(
        time_s=t,
        foot_z_m=np.where(contact, -2e-3 * (1 - ring), 0.2 - 4.905 * t**2),
        foot_r_m=2.26 + 0.09 * (1 - np.exp(-after / 0.04)),
        stroke_m=0.066 * (1 - np.exp(-after / 0.03)),
        stroke_max_m=0.066 * (1 - np.exp(-after / 0.03)),
        plastic_set_m=0.065 * (1 - np.exp(-after / 0.03)),
        pit_depth_m=2e-3 * (1 - np.exp(-after / 0.01)),
        slip_indicator=np.where(contact, (np.sin(200 * t) > 0.5).astype(float), 0.5),
        phase=np.where(contact, 2.0, 1.0),
        kinetic_J=550 * np.exp(-after / 0.05) * np.minimum(t / 0.2, 1) ** 2,
        potential_J=8725 - 900 * np.minimum(t / 0.25, 1),
        energy_residual_J=-1e-3 * t,
    )
    for c in COLUMNS:
        if c.startswith("diss_"):
            traj[c] = 200 * (1 - np.exp(-after / 0.05))
    outcomes = {
        "impacts": [{"start_s": 0.2, "end_s": 0.35}, {"start_s": 0.38, "end_s": None}],
        "touchdown_time_s": 0.2,
        "energy_initial_J": 8725.0,
    }
    return traj, outcomes


def test_writes_one_png_per_figure(tmp_path):
    traj, outcomes = synthetic_landing()
    paths = plot_landing(traj, outcomes, tmp_path / "figs", breakpoints_m=BREAKPOINTS)
    names = [p.name for p in paths]
    assert names == ["fig09_foot_velocity.png", "fig10_foot_position.png",
                     "fig12_foot_acceleration.png", "fig13_buffer.png", "fig14_body.png",
                     "fig15_forces.png", "fig16_energy.png"]
    for p in paths:
        assert p.is_file() and p.read_bytes()[:4] == b"\x89PNG", p
        assert p.stat().st_size > 20_000, p
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == sorted(names)  # no temps


def test_no_impacts_and_no_breakpoints(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    monkeypatch.setattr(Figure, "savefig", lambda self, fh, **kw: fh.write(b"\x89PNG"))  # fast
    traj, _ = synthetic_landing()
    assert len(plot_landing(traj, {}, tmp_path)) == 7


def test_missing_column_raises_and_writes_nothing(tmp_path):
    traj, outcomes = synthetic_landing()
    del traj["tangential_force_N"]
    with pytest.raises(ValueError, match="tangential_force_N"):
        plot_landing(traj, outcomes, tmp_path / "figs")
    assert not (tmp_path / "figs").exists()


def test_failed_render_leaves_no_partial_file(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    calls = []

    def failing_savefig(self, fh, **kwargs):
        calls.append(1)
        fh.write(b"\x89PNG half")
        if len(calls) == 2:
            raise RuntimeError("disk full")
        fh.write(b" rest")

    monkeypatch.setattr(Figure, "savefig", failing_savefig)
    traj, outcomes = synthetic_landing()
    with pytest.raises(RuntimeError, match="disk full"):
        plot_landing(traj, outcomes, tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["fig09_foot_velocity.png"]


def test_package_import_does_not_import_matplotlib():
    code = "import sys, jaxland, jaxland._plots; assert 'matplotlib' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
