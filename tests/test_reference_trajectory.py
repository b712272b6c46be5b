"""The unsmoothed code against a stored reference trajectory.

docs/integrators.md, "Gradient quality": "With both widths 0 (the default) the code is the
unsmoothed one, bit for bit". Comparing two Solvers that are the same object cannot fail;
this compares the smoothing-0 runs with numbers written once to
tests/data/reference_unsmoothed.json by

    .venv/bin/python tests/test_reference_trajectory.py --write [CASE ...]

(on jaxland at commit b261030, before the package refactor; chatter_verlet rewritten when
Verlet's implicit damping took the body's kick and its slip energy became a trapezoid, which
made it second order: it moved by up to 1.7e-7 of a channel's scale, towards the converged
run). The scenes are short and switch a
lot: the documented chatter scene (stiff, plastic ground, barely damped strut, 30 ms from
touchdown at 0.1 m drop: the foot bounces) with four integrators on the quarter model, and a
tilted, sliding landing on a slope on the full 3-D model (80 ms: all four feet down).
Tolerance: 1e-8 of each channel's largest magnitude. That admits round-off, which the chatter
amplifies (45 contact changes in 30 ms): after the package refactor (7a53b13) reordered
operations the quarter cases moved by up to 1.2e-10 (impulse, slip distance; 1.5e-11 for
Verlet, 3e-12 for Euler), the 3-D case by 0. It admits nothing a change of behaviour makes: the
1 um / 10 N smoothing moves these channels by 1e-6 and more (checked below); the contact law
smoothed over 1 um at width 0 moves the chatter runs by 0.5 of a channel's scale. A deliberate
change of the physics must rewrite the file, and say why in its commit.
"""

import json
import sys
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
import pytest

import jaxland as jl

REF = Path(__file__).parent / "data" / "reference_unsmoothed.json"
TOL = 1e-8  # of each channel's largest magnitude (module docstring)
T_END, SAVE_DT, DT = {"quarter": 0.03, "full": 0.08}, 1e-3, 1e-5
CHANNELS_QUARTER = ("stroke_m", "plastic_set_m", "strut_force_N", "honeycomb_force_N",
                    "aux_force_N", "normal_force_N", "tangential_force_N", "pit_depth_m",
                    "foot_r_m", "foot_z_m", "body_z_m", "body_vz_mps", "slip_distance_m",
                    "phase", "kinetic_J", "energy_residual_J")
CHANNELS_FULL = ("stroke_m", "normal_force_N", "tangential_force_N", "body_x_m", "body_y_m",
                 "body_z_m", "roll_deg", "pitch_deg", "yaw_deg",
                 "omega_x_radps", "omega_y_radps", "omega_z_radps", "stability_margin_m",
                 "kinetic_J", "energy_residual_J")
SUMMARY = ("max_stroke_m", "final_stroke_m", "peak_normal_force_N", "peak_strut_force_N",
           "peak_tangential_force_N", "peak_body_accel_mps2", "slip_distance_m",
           "n_contact_changes", "energy_dissipated_J", "peak_aux_force_N")
CASES = {  # name: (model, method)
    "chatter_euler": ("quarter", "euler"),
    "chatter_euler_implicit": ("quarter", "euler_implicit"),
    "chatter_verlet": ("quarter", "verlet"),
    "chatter_impulse": ("quarter", "impulse"),
    "tilted_full_euler": ("full", "euler"),
}


def _case(name):
    model, method = CASES[name]
    veh = jl.paper_vehicle()
    if model == "quarter":
        veh = eqx.tree_at(lambda v: (v.leg.D_b, v.ground.k, v.ground.gamma), veh,
                          (0.01, 2e7, 0.9))
        scene = jl.Scene.from_touchdown_speed(
            float(jl.Scene(drop_height=0.1).touchdown_speed(float(veh.g))))
    else:
        scene = jl.Scene(drop_height=0.0, sink_speed=2.0, horizontal_speed=1.0, heading=0.3,
                         roll=0.02, pitch=-0.01, yaw=0.2, pitch_rate=0.3, yaw_rate=0.5,
                         slope=0.02, slope_direction=1.0, friction=0.4)
    return veh, scene, model, method


def _run(name, **smoothing):
    veh, scene, model, method = _case(name)
    solver = jl.Solver(dt=DT, t_end=T_END[model], save_dt=SAVE_DT, method=method,
                       smoothing_m=smoothing.get("smoothing_m", 0.0),
                       smoothing_N=smoothing.get("smoothing_N", 0.0))
    tr, s = jax.jit(lambda v: jl.landing(v, scene, solver, model))(veh)
    channels = CHANNELS_QUARTER if model == "quarter" else CHANNELS_FULL
    return ({k: np.asarray(tr[k], dtype=float).tolist() for k in channels},
            {k: np.asarray(s[k], dtype=float).tolist() for k in SUMMARY})


@pytest.fixture(scope="module")
def reference():
    return json.loads(REF.read_text())


@pytest.fixture(scope="module")
def runs():
    return {name: _run(name) for name in CASES}


def _close(got, ref, what):
    got, ref = np.asarray(got, dtype=float), np.asarray(ref, dtype=float)
    assert got.shape == ref.shape, what
    scale = max(float(np.max(np.abs(ref))), 1e-300)
    np.testing.assert_allclose(got, ref, rtol=0, atol=TOL * scale, err_msg=what)


@pytest.mark.parametrize("name", list(CASES))
def test_unsmoothed_code_reproduces_the_stored_reference(name, runs, reference):
    tr, s = runs[name]
    ref = reference["cases"][name]
    for k, v in ref["trajectory"].items():
        _close(tr[k], v, f"{name}: {k}")
    for k, v in ref["summary"].items():
        _close(s[k], v, f"{name}: {k}")


def test_the_reference_can_see_the_smoothing(runs, reference):
    """With 1 um / 10 N the chatter run (Verlet) leaves the TOL band by far: so a smoothing
    that leaked into the width-0 path would be caught."""
    tr, _ = _run("chatter_verlet", smoothing_m=1e-6, smoothing_N=10.0)
    ref = reference["cases"]["chatter_verlet"]["trajectory"]["normal_force_N"]
    dev = np.max(np.abs(np.asarray(tr["normal_force_N"]) - np.asarray(ref)))
    assert dev > 100 * TOL * np.max(np.abs(ref)), dev


def test_reference_scenes_switch(reference):
    """The reference exercises the switches the smoothing touches: contact changes in every
    chatter case, every foot down and three slipping in the 3-D one."""
    for name, case in reference["cases"].items():
        if name.startswith("chatter"):
            assert case["summary"]["n_contact_changes"] >= 4, name
    full = reference["cases"]["tilted_full_euler"]["summary"]
    assert sum(s > 0 for s in full["slip_distance_m"]) >= 3 and min(full["peak_normal_force_N"]) > 0


def _write(names=()):
    """Rewrite the cases ``names`` (all if empty), keeping the others as stored."""
    cases = json.loads(REF.read_text())["cases"] if names and REF.exists() else {}
    for n in names or CASES:
        tr, s = _run(n)
        cases[n] = dict(model=CASES[n][0], method=CASES[n][1], trajectory=tr, summary=s)
    out = dict(generated_by="tests/test_reference_trajectory.py --write", jax=jax.__version__,
               dt_s=DT, t_end_s=T_END, save_dt_s=SAVE_DT,
               cases={n: cases[n] for n in CASES})
    REF.parent.mkdir(parents=True, exist_ok=True)
    REF.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {REF}")


if __name__ == "__main__":
    if "--write" in sys.argv:  # --write [CASE ...]
        _write(tuple(sys.argv[sys.argv.index("--write") + 1:]))
