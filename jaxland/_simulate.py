"""``simulate``: one landing from a scene and a vehicle, with outcomes and files.

``landing(vehicle, scene, solver)`` is the pure, jittable core (vmap it over scenes or vehicle
parameters, differentiate it). ``simulate(...)`` is the front door: it validates the inputs,
refuses a step above the stability limit, runs the compiled core, raises ``SimulationError`` on a
numerical failure, and returns a ``Landing`` with numpy arrays and a readable summary.
"""

from __future__ import annotations

import csv
import functools
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np

from . import _quarter
from ._config import paper_vehicle, validate_vehicle
from ._errors import ConfigError, SimulationError
from ._integrate import Solver, integrate, stable_step
from ._params import Vehicle
from ._scene import Scene

__all__ = ["landing", "simulate", "Landing", "impacts_from_events"]

# Contact gaps shorter than this are foot chatter within one impact, not a new impact [s]. The
# paper drop's hops after the first impact last 6-10 ms; chatter within an impact is sub-ms.
IMPACT_GAP_S = 1e-3


def landing(vehicle: Vehicle, scene: Scene, solver: Solver = Solver()):
    """Pure quarter-model landing: ``(trajectory, summary)`` dicts of jnp arrays."""
    return integrate(_quarter, vehicle, scene, solver)


@functools.partial(jax.jit, static_argnums=(2,))
def _landing_jit(vehicle, scene, solver):
    return landing(vehicle, scene, solver)


def impacts_from_events(event_times, n_changes, t_end, gap=IMPACT_GAP_S):
    """Group contact on/off times into impacts: a contact gap shorter than ``gap`` [s] is foot
    chatter inside one impact. Returns a list of (start_s, end_s or None if still in contact)."""
    n = int(min(n_changes, len(event_times)))
    times = [float(t) for t in event_times[:n]]
    spans = []
    for i in range(0, n, 2):
        start = times[i]
        end = times[i + 1] if i + 1 < n else None
        spans.append([start, end])
    merged = []
    for start, end in spans:
        if merged and merged[-1][1] is not None and start - merged[-1][1] < gap:
            merged[-1][1] = end
        else:
            merged.append([start, end])
    return [(s, e) for s, e in merged]


@dataclass
class Landing:
    """Result of ``simulate``: trajectory (numpy arrays, units in the names) and outcomes."""

    trajectory: dict
    outcomes: dict
    vehicle: Vehicle = field(repr=False)
    scene: Scene = field(repr=False)
    solver: Solver = field(repr=False)

    def to_csv(self, path) -> Path:
        """Write the trajectory as CSV (header: column names with units). Atomic."""
        path = Path(path)
        cols = list(self.trajectory)
        data = np.column_stack([np.asarray(self.trajectory[c], dtype=float) for c in cols])
        _atomic_write(path, lambda fh: _write_csv(fh, cols, data))
        return path

    def to_json(self, path) -> Path:
        """Write the outcomes as JSON. Atomic."""
        path = Path(path)
        text = json.dumps(self.outcomes, indent=2, default=float)
        _atomic_write(path, lambda fh: fh.write(text + "\n"))
        return path


def _write_csv(fh, cols, data):
    w = csv.writer(fh)
    w.writerow(cols)
    for row in data:
        w.writerow([f"{x:.9g}" for x in row])


def _atomic_write(path: Path, writer):
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", newline="") as fh:
            writer(fh)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _outcomes(summary: dict, traj: dict, vehicle: Vehicle, scene: Scene, solver: Solver) -> dict:
    s = {k: np.asarray(v) for k, v in summary.items()}
    impacts = impacts_from_events(s["event_times_s"], s["n_contact_changes"], solver.t_end)
    hc = vehicle.honeycomb
    t = traj["time_s"]
    first_end = impacts[0][1] if impacts and impacts[0][1] is not None else None
    if first_end is not None:
        i_end = int(np.searchsorted(t, first_end))
        i_end = min(i_end, len(t) - 1)
        stroke_first = float(np.max(traj["stroke_m"][: i_end + 1]))
        foot_v_end = float(traj["foot_vz_mps"][max(i_end - 1, 0)])
    else:
        stroke_first = float(s["max_stroke_m"])
        foot_v_end = None
    dissipated = float(s["energy_dissipated_J"])
    out = {
        "model": "quarter",
        "drop_height_m": float(scene.drop_height),
        "sink_speed_mps": float(scene.sink_speed),
        "touchdown_speed_mps": float(scene.touchdown_speed(float(vehicle.g))),
        "dt_s": solver.dt,
        "t_end_s": solver.t_end,
        "touchdown_time_s": impacts[0][0] if impacts else None,
        "impacts": [{"start_s": a, "end_s": b} for a, b in impacts],
        "n_impacts": len(impacts),
        "n_contact_changes": int(s["n_contact_changes"]),
        "first_impact_stroke_m": stroke_first,
        "foot_vz_end_first_impact_mps": foot_v_end,
        "max_stroke_m": float(s["max_stroke_m"]),
        "final_stroke_m": float(s["final_stroke_m"]),
        "final_plastic_set_m": float(s["final_plastic_set_m"]),
        "final_pit_depth_m": float(s["final_pit_depth_m"]),
        "secondary_honeycomb_engaged": bool(s["max_stroke_m"] > float(hc.x_L2)),
        "bottomed_out": bool(s["max_stroke_m"] > float(hc.x_L4)),
        "slip_distance_m": float(s["slip_distance_m"]),
        "energy_initial_J": float(s["energy_initial_J"]),
        "energy_dissipated_J": dissipated,
        "energy_closure_max_J": float(s["energy_closure_max_J"]),
        "energy_closure_rel": float(s["energy_closure_max_J"]) / max(dissipated, 1e-12),
    }
    for k, v in s.items():
        if k.startswith("peak_"):
            out[k] = float(v)
    return out


def simulate(scene: Scene | None = None, vehicle: Vehicle | None = None, *,
             dt: float = 1e-5, t_end: float = 1.2, save_dt: float | None = None) -> Landing:
    """Simulate one symmetric landing of ``vehicle`` (default: the paper's) in ``scene``
    (default: the paper's 0.2 m drop) with symplectic Euler at step ``dt`` [s] for ``t_end`` [s],
    sampling the trajectory every ``save_dt`` [s] (default: max(1e-4 s, dt)).

    Raises ``ConfigError`` for invalid inputs or a step above the stability limit and
    ``SimulationError`` if the integration blows up.
    """
    scene = Scene() if scene is None else scene
    vehicle = paper_vehicle() if vehicle is None else vehicle
    scene.validate()
    validate_vehicle(vehicle)
    if save_dt is None and isinstance(dt, (int, float)):
        save_dt = max(1e-4, dt)
    solver = Solver(dt=dt, t_end=t_end, save_dt=save_dt)
    solver.validate_values()
    limit = float(stable_step(vehicle))
    if dt > limit:
        raise ConfigError("solver.dt", dt, f"exceeds the stability limit {limit:.3g} s of "
                          "symplectic Euler for this vehicle (stiffest spring and strut damping "
                          "on the foot); use dt <= that")
    solver.validate()
    traj, summary = _landing_jit(vehicle, scene, solver)
    traj = {k: np.asarray(traj[k]) for k in _quarter.COLUMNS}
    if bool(summary["failed"]):
        raise SimulationError(
            f"integration failed at t = {float(summary['failure_time_s']):.6g} s (non-finite "
            f"state or energy ledger off by more than 10 %) with dt = {dt:.3g} s; the estimated "
            f"stability limit is {limit:.3g} s: reduce dt")
    return Landing(traj, _outcomes(summary, traj, vehicle, scene, solver), vehicle, scene, solver)
