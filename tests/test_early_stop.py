"""Early stop (``Solver(early_stop=True)``): a landing stopped once the settle bound holds
(jaxland._solvers._settle) has every Monte Carlo outcome of the same landing run to t_end, and
a landing that does not settle runs to t_end unchanged."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxland as jl

DEG = np.pi / 180.0
# the Monte Carlo outcomes (per leg where the model has legs), as without early stop
OUTCOMES = ("max_stroke_m", "peak_strut_force_N", "peak_normal_force_N",
            "peak_honeycomb_force_N", "slip_distance_m", "peak_body_accel_mps2", "result",
            "tipped", "bottomed", "peak_margin_deficit_m", "peak_tilt_deg")


def _both(model, scenes, t_end, dt=1e-5, method="euler"):
    vehicle = jl.paper_vehicle()

    def run(early):
        solver = jl.Solver(dt=dt, t_end=t_end, save_dt=t_end, early_stop=early,
                           method=method).validate()
        return jax.device_get(jax.jit(
            lambda sc: jl.landings(vehicle, sc, solver, model)[1])(scenes))

    return run(False), run(True)


def _check(full, early, t_end, n_settled):
    settled = np.isfinite(early["settled_time_s"])
    assert settled.sum() >= n_settled, early["settled_time_s"]
    np.testing.assert_array_equal(early["t_end_s"][settled], early["settled_time_s"][settled])
    assert np.all(early["t_end_s"][settled] < t_end)
    np.testing.assert_allclose(early["t_end_s"][~settled], t_end, rtol=1e-9)
    for k in OUTCOMES:  # the same up to how XLA compiles either program
        if k in full:
            np.testing.assert_allclose(early[k], full[k], rtol=1e-9, atol=0, err_msg=k)
    # the ledger closure is judged up to the settle time: the same verdict, and the same
    # value to the energy the ringing still dissipates
    closed = full["ledger_error_rel"] <= jl.CLOSURE_LIMIT
    np.testing.assert_array_equal(early["ledger_error_rel"] <= jl.CLOSURE_LIMIT, closed)
    np.testing.assert_allclose(early["ledger_error_rel"], full["ledger_error_rel"], rtol=0.05)
    for k, v in full.items():  # a landing that did not settle ran to the end unchanged
        np.testing.assert_allclose(np.asarray(early[k])[~settled], np.asarray(v)[~settled],
                                   rtol=1e-9, atol=1e-300, err_msg=k)


@pytest.mark.parametrize("method,dt", [("euler", 1e-5), ("leapfrog", 2e-5)])
def test_quarter_landings_stop_when_settled_with_the_same_outcomes(method, dt):
    """The paper's 0.2 m drop and touchdowns of 1-4 m/s (the hardest crushes into the second
    stage), light and heavy, for 3 s: they settle after 1.7-3 s with every outcome equal to
    the run to 3 s (also under the leapfrog, which carries its last evaluation)."""
    t_end = 3.0
    scenes = jl.Scene.batch(
        drop_height=jnp.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.0]),
        sink_speed=jnp.array([0.0, 1.0, 1.8, 2.3, 3.0, 4.0]),
        mass_scale=jnp.array([1.0, 1.05, 0.95, 1.0, 1.04, 0.97]))
    full, early = _both("quarter", scenes, t_end, dt, method)
    assert full["max_stroke_m"].max() > float(jl.paper_vehicle().honeycomb.x_L3)
    _check(full, early, t_end, n_settled=4)


def test_full_landings_stop_when_settled_with_the_same_outcomes():
    """The 3-D model at dt = 2e-5 s: the paper's drop settles after ~4 s; a tilted landing on
    a slope keeps energy in its sway on the tangential springs beyond any bound within 4.5 s
    and runs to the end, unchanged."""
    t_end = 4.5
    scenes = jl.Scene.batch(
        drop_height=jnp.array([0.2, 0.0]), sink_speed=jnp.array([0.0, 2.0]),
        roll=jnp.array([0.0, 2.0 * DEG]), slope=jnp.array([0.0, 3.0 * DEG]),
        horizontal_speed=jnp.array([0.0, 0.8]))
    full, early = _both("full", scenes, t_end, dt=2e-5)
    _check(full, early, t_end, n_settled=1)
    assert not np.isfinite(early["settled_time_s"][1])


def test_early_stop_needs_a_run_without_trajectory_and_a_fixed_step():
    with pytest.raises(jl.ConfigError, match="save_dt = t_end"):
        jl.Solver(dt=1e-5, t_end=0.5, early_stop=True).validate()
    with pytest.raises(jl.ConfigError, match="fixed-step"):
        jl.Solver(dt=1e-5, t_end=0.5, save_dt=0.5, method="tsit5", early_stop=True).validate()
    jl.Solver(dt=1e-5, t_end=0.5, save_dt=0.5, method="verlet", early_stop=True).validate()


def test_early_stop_differentiates_forward_and_refuses_reverse_by_name():
    """The early stop runs in a while loop, which JAX differentiates forward only: jacfwd
    agrees with a central difference, and jax.grad is refused as solver.early_stop, where
    JAX's own error named no setting."""
    solver = jl.Solver(dt=1e-4, t_end=0.05, save_dt=0.05, early_stop=True)

    def stroke(v):
        scene = jl.Scene(drop_height=0.0, sink_speed=v)
        return jl.landing(jl.paper_vehicle(), scene, solver, "quarter")[1]["max_stroke_m"]

    d = float(jax.jacfwd(stroke)(2.0))
    h, at = 1e-6, jax.jit(stroke)
    assert d == pytest.approx(float(at(2.0 + h) - at(2.0 - h)) / (2 * h), rel=1e-4)
    with pytest.raises(jl.ConfigError, match=r"solver\.early_stop = True: has no reverse-mode "
                                             r"derivative .* run without early_stop"):
        jax.grad(stroke)(2.0)
