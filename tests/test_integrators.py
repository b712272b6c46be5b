"""The integrator family: agreement with a converged reference, stability boundaries pinned
against theory (just inside: accurate; just outside: detected, never returned silently),
refusals with the limit stated, adaptive stalls surfaced, and differentiability of each method.

The theory is ``jaxland.stable_step`` (the stiffest springs and the damping on the 1 kg foot,
per method); the boundaries below were measured on the paper drop and are pinned here.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxland as jl
from jaxland import _simulate

VEH = jl.paper_vehicle()
SCENE = jl.Scene()  # the paper's 0.2 m drop: touchdown at 0.2 s, first peak stroke by 0.3 s
T_END = 0.4
FIXED = ("euler", "euler_implicit", "verlet", "leapfrog")


def _run(method, dt, vehicle=VEH, scene=SCENE, t_end=T_END, **kw):
    save = max(1, round(1e-3 / dt)) * dt
    solver = jl.Solver(dt=dt, t_end=t_end, save_dt=save, method=jl.integrator(method, **kw))
    return jax.jit(lambda v: jl.landing(v, scene, solver, "quarter"))(vehicle)[1]


@pytest.fixture(scope="module")
def reference():
    """Converged reference: symplectic Euler at 1.25e-6 s (it moves by < 2e-6 relative from
    2.5e-6 s, checked here)."""
    fine, finer = _run("euler", 2.5e-6), _run("euler", 1.25e-6)
    ref = float(finer["max_stroke_m"])
    assert abs(float(fine["max_stroke_m"]) / ref - 1.0) < 2e-6
    return ref


@pytest.mark.parametrize("method,kw,tol", [
    ("euler", {}, 2e-4), ("euler_implicit", {}, 2e-4), ("verlet", {}, 2e-4),
    ("leapfrog", {}, 2e-4), ("impulse", {"impulse": 0.05}, 2e-4),
    ("tsit5", {"rtol": 1e-6, "atol": 1e-9}, 1e-4),
])
def test_every_method_converges_to_the_reference(reference, method, kw, tol):
    s = _run(method, 1e-5, **kw)
    assert not bool(s["failed"]) and bool(s["solver_ok"])
    assert abs(float(s["max_stroke_m"]) / reference - 1.0) < tol
    assert float(s["ledger_error_rel"]) < 1e-3


@pytest.mark.parametrize("method,inside,outside", [
    ("euler", 0.95, 1.1),  # fails between 1.05 and 1.1 x theory (measured)
    ("verlet", 0.95, 1.1),  # fails between 1.05 and 1.1 x theory
    ("leapfrog", 0.95, 1.1),  # fails between 1.05 and 1.1 x theory
    ("euler_implicit", 0.95, 1.5),  # theory is conservative here: fails at 1.35-1.4 x
])
def test_stability_boundary_of_fixed_step_methods(reference, method, inside, outside):
    limit = float(jl.stable_step(VEH, method=method))
    ok = _run(method, inside * limit)
    assert not bool(ok["failed"])
    assert abs(float(ok["max_stroke_m"]) / reference - 1.0) < 5e-3
    bad = _run(method, outside * limit)
    assert bool(bad["failed"]) or float(bad["ledger_error_rel"]) > _simulate.CLOSURE_LIMIT


def test_implicit_damping_moves_the_limit_from_damping_to_springs():
    """Explicit Euler is limited by the strut damping D_b F2 on the foot; with the damping
    implicit only the springs remain: 2 / omega, omega^2 = sum k / m2."""
    hc, leg, gr = VEH.honeycomb, VEH.leg, VEH.ground
    w2 = float(max(hc.k_b1, hc.k_b3, leg.k_topout) + leg.k_a + gr.k / (1 - gr.gamma)
               + gr.k_tan) / float(VEH.m_foot)
    c = float(leg.D_b * hc.F2) / float(VEH.m_foot)
    assert float(jl.stable_step(VEH)) < 2.0 / c < 2.0 / np.sqrt(w2)
    np.testing.assert_allclose(float(jl.stable_step(VEH, method="verlet")), 2 / np.sqrt(w2),
                               rtol=1e-3)  # the ground damping chi F2 is all that is left


@pytest.mark.parametrize("d_impulse,outside", [(0.05, 1.25), (0.8, 2.0)])
def test_impulse_method_cap_boundary(reference, d_impulse, outside):
    """The impulse method's explicit step dt = min(dI / F, cap): its damping limit is on dI
    (c dt <= (D_b + chi) dI / m2 whatever the force), so the cap limit depends on dI. The bound
    assumes the worst damping and the cap coincide; at a large dI that is conservative (measured:
    dI = 0.05 N s fails at 1.1-1.25 x the bound, dI = 0.8 N s at 1.6-2 x)."""
    cap = float(jl.stable_step(VEH, method="impulse", impulse=d_impulse))
    ok = _run("impulse", 0.9 * cap, impulse=d_impulse)
    assert not bool(ok["failed"])
    assert abs(float(ok["max_stroke_m"]) / reference - 1.0) < 5e-3
    bad = _run("impulse", outside * cap, impulse=d_impulse)
    assert bool(bad["failed"]) or float(bad["ledger_error_rel"]) > _simulate.CLOSURE_LIMIT


def test_impulse_step_beyond_the_damping_limit_is_refused():
    limit = 2 * float(VEH.m_foot) / float(VEH.leg.D_b + VEH.ground.chi)
    assert float(jl.stable_step(VEH, method="impulse", impulse=1.01 * limit)) == 0.0
    with pytest.raises(jl.ConfigError, match=r"solver\.impulse.*2 m2 / \(D_b \+ chi\)"):
        jl.simulate(method="impulse", impulse=1.01 * limit, t_end=0.1)


@pytest.mark.parametrize("method", ["euler", "euler_implicit", "verlet", "leapfrog", "impulse"])
def test_a_step_above_the_limit_is_refused_with_the_limit_stated(method):
    limit = float(jl.stable_step(VEH, method=method))
    with pytest.raises(jl.ConfigError, match=rf"solver\.dt.*stability limit {limit:.3g} s "
                                             rf"of {method}"):
        jl.simulate(dt=1.2 * limit, t_end=0.1, method=method)


def test_the_step_a_refusal_offers_is_below_the_limit():
    """The euler limit of the paper vehicle, 1.33676e-4 s, prints as 0.000134 s; the step the
    refusal offers must be one the check accepts, so it is the limit rounded down."""
    limit = float(jl.stable_step(VEH, method="euler"))
    with pytest.raises(jl.ConfigError) as err:
        jl.simulate(dt=float(f"{limit:.3g}"), t_end=0.01)
    offered = float(str(err.value).split("use dt <= ")[1].split(" s")[0])
    assert limit * 0.99 < offered <= limit
    jl.simulate(dt=offered, t_end=0.01)  # accepted


def test_tsit5_first_step_above_its_cap_is_refused():
    """tsit5's dt is its first step, and the unit of its default output interval: a first step
    of 0.9 s ran a 1 s landing to 1.8 s. It must not exceed the step cap."""
    from jaxland._models import MODELS
    from jaxland._solvers._tsit5 import step_cap

    cap = float(step_cap(MODELS["quarter"], VEH))
    with pytest.raises(jl.ConfigError, match=r"solver\.dt = 0\.9: is tsit5's first step and "
                                             r"must be <= its step cap"):
        jl.simulate(dt=0.9, t_end=1.0, method="tsit5")
    with pytest.raises(jl.ConfigError, match="step cap"):
        jl.simulate(dt=1.01 * cap, t_end=0.01, method="tsit5")


def test_blow_up_past_the_limit_is_raised_by_simulate(monkeypatch):
    limit = float(jl.stable_step(VEH, method="verlet"))
    monkeypatch.setattr(_simulate, "stable_step", lambda v, **kw: 1.0)
    with pytest.raises(jl.SimulationError, match="rerun with dt"):
        jl.simulate(dt=1.3 * limit, t_end=T_END, save_dt=1.3 * limit, method="verlet")


def test_adaptive_stall_is_reported():
    with pytest.raises(jl.SimulationError, match="max_steps = 200 reached") as err:
        jl.simulate(method="tsit5", max_steps=200, t_end=T_END, rtol=1e-8, atol=1e-11)
    t_stop = float(str(err.value).split("stopped at t = ")[1].split(" s")[0])
    assert 0.0 < t_stop < T_END  # where it stopped, not the unreached save points' inf
    # a tolerance no float64 step can meet is refused before the run (it stalled there)
    with pytest.raises(jl.ConfigError, match=r"solver\.rtol = 1e-20: must be >= 1e-14"):
        jl.simulate(method="tsit5", t_end=T_END, rtol=1e-20)


@pytest.mark.parametrize("method", ["euler_implicit", "verlet"])
def test_saved_forces_are_the_ones_applied(method):
    """The trajectory reports the forces with the method's implicit damping, as the steps
    apply them: no saved value exceeds the running peak over all steps."""
    dt = 0.9 * float(jl.stable_step(VEH, method=method))
    solver = jl.Solver(dt=dt, t_end=T_END, save_dt=dt, method=method)
    traj, s = jax.jit(lambda v: jl.landing(v, SCENE, solver, "quarter"))(VEH)
    for col, peak in (("foot_az_mps2", "peak_foot_accel_normal_mps2"),
                      ("body_az_mps2", "peak_body_accel_mps2"),
                      ("strut_force_N", "peak_strut_force_N")):
        assert float(np.max(np.abs(traj[col]))) <= float(s[peak]) * (1 + 1e-12), col


@pytest.mark.parametrize("method", ["verlet", "leapfrog"])
def test_full_model_takes_fixed_step_methods_and_refuses_the_others(method):
    scene = jl.Scene(drop_height=0.05)
    solver = jl.Solver(dt=1e-5, t_end=0.15, save_dt=1e-3, method=method)
    full = jax.jit(lambda v: jl.landing(v, scene, solver, "full"))(VEH)[1]
    quarter = jax.jit(lambda v: jl.landing(v, scene, solver, "quarter"))(VEH)[1]
    np.testing.assert_allclose(np.asarray(full["max_stroke_m"]),
                               float(quarter["max_stroke_m"]), rtol=1e-8)
    for method in ("impulse", "tsit5"):
        with pytest.raises(jl.ConfigError, match="quarter model only"):
            jl.landing(VEH, scene, jl.Solver(method=method), "full")


@pytest.mark.parametrize("method,adjoint,rtol", [
    ("euler", "forward", 1e-3), ("euler_implicit", "forward", 1e-3), ("verlet", "forward", 1e-3),
    ("leapfrog", "forward", 1e-3), ("impulse", "forward", 1e-3), ("impulse", "reverse", 1e-3),
])
def test_each_method_differentiates(method, adjoint, rtol):
    """jacfwd (forward) or grad (reverse) of max stroke in D_b and F1 is finite and matches
    central differences at the first impact at two neighbouring steps, h = 1e-5 and 1e-6
    relative (both must agree: one lucky secant does not count). Measured: <= 6.7e-5 over all
    methods and both steps; asserted 1e-3. Fuller gradient quality is measured in
    benchmarks/gradient_quality.py and tests/test_gradient_quality.py."""
    options = {} if method in FIXED else {"adjoint": adjoint}
    solver = jl.Solver(dt=1e-5, t_end=0.3, save_dt=1e-3, method=jl.integrator(method, **options))

    def stroke(p):
        veh = eqx.tree_at(lambda v: (v.leg.D_b, v.honeycomb.F1), VEH,
                          (VEH.leg.D_b * p[0], VEH.honeycomb.F1 * p[1]))
        return jl.landing(veh, SCENE, solver, "quarter")[1]["max_stroke_m"]

    p0 = np.ones(2)
    diff = jax.jacfwd if adjoint == "forward" else jax.grad
    g = np.asarray(jax.jit(diff(stroke))(p0))
    f = jax.jit(stroke)
    assert np.all(np.isfinite(g))
    for h in (1e-5, 1e-6):
        fd = np.array([(f(p0 + h * e) - f(p0 - h * e)) / (2 * h) for e in np.eye(2)])
        np.testing.assert_allclose(g, fd, rtol=rtol, err_msg=f"h = {h}")


@pytest.mark.parametrize("adjoint,diff", [("forward", jax.jacfwd), ("reverse", jax.grad)])
def test_tsit5_refuses_to_be_differentiated(adjoint, diff):
    """tsit5's sensitivities miss the contact switches' jumps (errors of order one,
    benchmarks/gradient_quality.py): taking them raises, naming the method; the forward run
    stays available."""
    solver = jl.Solver(dt=1e-5, t_end=0.3, save_dt=1e-3,
                       method=jl.integrator("tsit5", adjoint=adjoint))

    def stroke(d_b):
        veh = eqx.tree_at(lambda v: v.leg.D_b, VEH, VEH.leg.D_b * d_b)
        return jl.landing(veh, SCENE, solver, "quarter")[1]["max_stroke_m"]

    with pytest.raises(jl.ConfigError, match="tsit5.*cannot be differentiated"):
        diff(stroke)(1.0)
    assert np.isfinite(float(jax.jit(stroke)(1.0)))


def test_impulse_forward_adjoint_refuses_grad_by_name_and_keeps_forward_mode():
    """The impulse method's forward-mode while loop has no reverse-mode derivative: jax.grad
    is refused naming solver.adjoint and the option that has one, not with JAX's message about
    while loops; jacfwd, also under vmap, still runs (its values: the test above)."""
    solver = jl.Solver(dt=1e-5, t_end=0.3, save_dt=1e-3, method=jl.integrator("impulse"))

    def stroke(d_b):
        veh = eqx.tree_at(lambda v: v.leg.D_b, VEH, VEH.leg.D_b * d_b)
        return jl.landing(veh, SCENE, solver, "quarter")[1]["max_stroke_m"]

    with pytest.raises(jl.ConfigError, match=r"solver\.adjoint = 'forward'.*jax\.grad.*"
                                             r"Impulse\(adjoint='reverse'\)"):
        jax.grad(stroke)(1.0)
    batch = np.asarray(jax.jit(jax.vmap(jax.jacfwd(stroke)))(jnp.array([0.9, 1.1])))
    alone = [float(jax.jit(jax.jacfwd(stroke))(d)) for d in (0.9, 1.1)]
    assert np.all(batch != 0.0)
    np.testing.assert_allclose(batch, alone, rtol=1e-12)


def test_impulse_reverse_adjoint_refuses_jacfwd_by_name_and_keeps_grad():
    """The mirror: the reverse adjoint's checkpointed while loop has no forward-mode
    derivative, and jax.jacfwd (also under jit) is refused naming solver.adjoint and the
    option that has one, not with JAX's message about custom_vjp functions; jax.grad runs
    and agrees with a central difference."""
    solver = jl.Solver(dt=1e-5, t_end=0.3, save_dt=1e-3,
                       method=jl.integrator("impulse", adjoint="reverse"))

    def stroke(d_b):
        veh = eqx.tree_at(lambda v: v.leg.D_b, VEH, VEH.leg.D_b * d_b)
        return jl.landing(veh, SCENE, solver, "quarter")[1]["max_stroke_m"]

    for diff in (jax.jacfwd, lambda f: jax.jit(jax.jacfwd(f))):
        with pytest.raises(jl.ConfigError, match=r"solver\.adjoint = 'reverse'.*jax\.jacfwd.*"
                                                 r"Impulse\(adjoint='forward'\)"):
            diff(stroke)(1.0)
    grad = float(jax.jit(jax.grad(stroke))(1.0))
    f = jax.jit(stroke)
    fd = (float(f(1.0 + 1e-4)) - float(f(1.0 - 1e-4))) / 2e-4
    assert grad < 0.0 and grad == pytest.approx(fd, rel=1e-3)


def test_default_step_is_chosen_from_the_physics():
    """Without dt, simulate takes 1e-5 s, or half the method's stability limit for a stiffer
    vehicle, on a whole fraction of 1e-4 s; that step runs and is inside the limit."""
    assert _simulate.default_step(VEH) == 1e-5
    stiff = eqx.tree_at(lambda v: v.honeycomb.k_b1, VEH, 1e11)  # 1e4 x the paper k_b1
    limit = float(jl.stable_step(stiff))
    dt = _simulate.default_step(stiff)
    assert 0.4 * limit < dt <= 0.5 * limit
    assert abs(1e-4 / dt - round(1e-4 / dt)) < 1e-9
    res = jl.simulate(jl.Scene(drop_height=0.02), stiff, t_end=0.1)
    assert res.outcomes["dt_s"] == dt and res.outcomes["energy_closure_rel"] < 1e-2
    assert _simulate.default_step(stiff, "verlet") > dt  # implicit damping: a larger step


@pytest.mark.parametrize("method", ["verlet", "leapfrog"])
def test_second_order_methods_keep_their_order_on_the_paper_drop(method):
    """Verlet and the leapfrog (one evaluation per step, the strut damping implicit over its
    second half kick) keep second order on a landing: on the paper drop's first impact (from
    touchdown, 0.2 s) as dt halves from 4e-5 s to 5e-6 s, the max stroke's successive
    changes and the ledger's worst residual shrink at order >= 1.8 (measured: verlet 2.0 and
    1.9, leapfrog 1.92 and 1.88; verlet with the body held still in the implicit strut damping
    about 1.1 and 1.0, the leapfrog with the damping explicit at the half-step velocity 1.5 and
    1.0)."""
    dts = np.array([4e-5, 2e-5, 1e-5, 5e-6])
    scene = jl.Scene.from_touchdown_speed(float(SCENE.touchdown_speed(float(VEH.g))))
    runs = [_run(method, float(dt), scene=scene, t_end=0.2) for dt in dts]
    stroke = np.array([float(s["max_stroke_m"]) for s in runs])
    ledger = np.array([float(s["energy_closure_max_J"]) for s in runs])

    def order(d, y):
        return np.polyfit(np.log(d), np.log(np.abs(y)), 1)[0]

    assert order(dts[:-1], np.diff(stroke)) >= 1.8, np.diff(stroke)
    assert order(dts, ledger) >= 1.8, ledger


TSIT5_PEAKS = ("peak_normal_force_N", "peak_tangential_force_N", "peak_strut_force_N",
               "peak_honeycomb_force_N", "peak_buffer_velocity_mps", "peak_body_accel_mps2",
               "peak_foot_accel_mps2", "peak_aux_force_N")


def test_tsit5_peaks_and_events_do_not_depend_on_the_output_interval():
    """tsit5 takes its peaks, event log and touchdown at every accepted step, as the fixed-step
    methods take them at every step: at an output interval of 1e-4 s and of the whole landing
    (one save point) they are the same, and match velocity Verlet at 1e-5 s. Measured (rtol
    1e-6, paper drop): every peak within 1.2e-3 of Verlet (the auxiliary strut force; the rest
    within 1.8e-4), Verlet itself within 7e-5 of Verlet at 2e-6 s; touchdown 3e-7 s after the
    free fall's closed form (a jump time of the step controller); the first impact's end 5e-6 s
    from Verlet's. Asserted: 2e-3, 1e-6 s, and for the lift-off, found at the end of an
    accepted step, tsit5's step cap (1 / omega of the foot, 2.2e-4 s here) rounded down to
    2e-4 s. Read at the save points only, the one-save run reported the peaks of t = 0.4 s
    (all off by more than half) and a touchdown at 0.4 s; with the step capped at the output
    interval instead of the foot's time scale, the two runs' peaks differed by 3e-5."""
    ref = _run("verlet", 1e-5)
    t_touch = float(np.sqrt(2.0 * SCENE.drop_height / float(VEH.g)))
    runs = []
    for save_dt in (1e-4, T_END):
        solver = jl.Solver(dt=1e-5, t_end=T_END, save_dt=save_dt, method="tsit5")
        s = jax.jit(lambda v, solver=solver: jl.landing(v, SCENE, solver, "quarter"))(VEH)[1]
        assert bool(s["solver_ok"]) and not bool(s["failed"])
        for k in TSIT5_PEAKS:
            assert abs(float(s[k]) / float(ref[k]) - 1.0) < 2e-3, (save_dt, k)
        events = np.asarray(s["event_times_s"])
        assert 0.0 <= events[0] - t_touch < 1e-6, save_dt
        assert abs(events[1] - float(ref["event_times_s"][1])) < 2e-4, save_dt
        runs.append(s)
    for k in TSIT5_PEAKS + ("max_stroke_m", "n_contact_changes"):
        np.testing.assert_allclose(float(runs[1][k]), float(runs[0][k]), rtol=1e-12, err_msg=k)
    np.testing.assert_allclose(runs[1]["event_times_s"], runs[0]["event_times_s"], rtol=1e-12)
