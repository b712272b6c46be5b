"""plot_landing_3d: five readable PNGs of a 3-D landing, clear errors (no simulation)."""

import numpy as np
import pytest

import jaxland as jl
from jaxland import FullModel
from jaxland._plots import PER_LEG_COLUMNS, REQUIRED_COLUMNS_3D, plot_landing_3d

COLUMNS = FullModel.COLUMNS

N, LEGS = 300, 4
NAMES = ["fig3d_attitude.png", "fig3d_legs.png", "fig3d_body.png", "fig3d_energy.png",
         "fig3d_views.png"]


def synthetic_landing():
    """Plausible curves for every column: a drop with touchdown at 0.2 s, legs that crush by
    different amounts, feet that slide a little; per-leg columns are (N, LEGS)."""
    t = np.linspace(0.0, 0.6, N)
    after = np.clip(t - 0.2, 0.0, None)
    ring = np.exp(-after / 0.05) * np.sin(2 * np.pi * 12 * after)
    contact = (t >= 0.2)[:, None]
    scale = np.array([1.0, 0.8, 0.7, 0.9])  # per leg
    rise = (1 - np.exp(-after / 0.03))[:, None] * scale
    traj = {c: 0.1 * ring + 0.01 * np.cos(7 * t) for c in REQUIRED_COLUMNS_3D}
    psi = 2 * np.pi * np.arange(LEGS) / LEGS
    slide = 0.1 * (1 - np.exp(-after / 0.1))
    z_body = np.where(t < 0.2, 3.2 - 4.905 * t**2, 3.0 - 0.2 * (1 - np.exp(-after / 0.05)))
    traj.update(
        time_s=t,
        body_x_m=0.5 * t, body_y_m=0.1 * t, body_z_m=z_body,
        roll_deg=2.0 * np.exp(-after / 0.1), pitch_deg=-3.0 + 2.0 * np.minimum(t / 0.3, 1),
        yaw_deg=10.0 + 5.0 * slide, tilt_deg=3.0 * np.exp(-after / 0.1),
        stability_margin_m=1.4 - 2.0 * slide,
        stroke_m=0.09 * rise,
        strut_force_N=12e3 * rise * np.exp(-after / 0.2)[:, None],
        aux_force_N=-8e3 * rise * np.exp(-after / 0.2)[:, None],
        normal_force_N=np.where(contact, 10e3 * (1 + ring[:, None]) * scale, 0.0),
        tangential_force_N=np.where(contact, 3e3 * np.abs(ring)[:, None] * scale, 0.0),
        slip_indicator=np.where(contact, (np.sin(90 * t) > 0.3)[:, None] * 1.0, 0.5)
        * np.ones((N, LEGS)),
        foot_x_m=2.26 * np.cos(psi) + (0.5 * t + slide)[:, None],
        foot_y_m=2.26 * np.sin(psi) + 0.1 * t[:, None],
        foot_z_m=np.where(contact, -2e-3 * rise, (z_body - 2.98)[:, None]),
        kinetic_J=20e3 * np.exp(-after / 0.05) * np.minimum(t / 0.2, 1) ** 2,
        potential_J=38e3 - 7e3 * np.minimum(t / 0.3, 1),
        energy_residual_J=-1e-3 * t,
    )
    for c in REQUIRED_COLUMNS_3D:
        if c.startswith("diss_"):
            traj[c] = 1e3 * (1 - np.exp(-after / 0.05))
    outcomes = {"impacts": [{"start_s": 0.2, "end_s": None}], "touchdown_time_s": 0.2,
                "energy_initial_J": 38e3}
    return traj, outcomes


def test_writes_five_pngs(tmp_path):
    traj, outcomes = synthetic_landing()
    assert all(traj[c].shape == (N, LEGS) for c in PER_LEG_COLUMNS)
    paths = plot_landing_3d(traj, outcomes, tmp_path / "figs", vehicle=jl.paper_vehicle(),
                            scene=jl.Scene())
    assert [p.name for p in paths] == NAMES
    for p in paths:
        assert p.is_file() and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", p
        assert p.stat().st_size > 20_000, p
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == sorted(NAMES)  # no temps


def test_no_touchdown_no_impacts_and_a_slope(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    monkeypatch.setattr(Figure, "savefig", lambda self, fh, **kw: fh.write(b"\x89PNG"))  # fast
    traj, _ = synthetic_landing()
    paths = plot_landing_3d(traj, {}, tmp_path, vehicle=jl.paper_vehicle(),
                            scene=jl.Scene(slope=0.1, slope_direction=1.0))
    assert [p.name for p in paths] == NAMES


def test_missing_column_raises_and_writes_nothing(tmp_path):
    traj, outcomes = synthetic_landing()
    del traj["slip_indicator"], traj["stability_margin_m"]
    with pytest.raises(ValueError, match="stability_margin_m, slip_indicator"):
        plot_landing_3d(traj, outcomes, tmp_path / "figs", vehicle=jl.paper_vehicle(),
                        scene=jl.Scene())
    assert not (tmp_path / "figs").exists()


def test_per_leg_column_of_wrong_shape_raises(tmp_path):
    traj, outcomes = synthetic_landing()
    traj["stroke_m"] = traj["stroke_m"][:, 0]  # one leg only, 1-D
    with pytest.raises(ValueError, match=r"stroke_m .*\(300, 4\)"):
        plot_landing_3d(traj, outcomes, tmp_path / "figs", vehicle=jl.paper_vehicle(),
                        scene=jl.Scene())
    assert not (tmp_path / "figs").exists()


def test_required_columns_are_what_the_3d_model_records():
    assert set(REQUIRED_COLUMNS_3D) <= set(COLUMNS)
