"""Lean bookkeeping (``Solver.peaks``, ``Solver.ledger_every``, ``Solver.event_log``): a
landing that keeps fewer running maxima, checks its ledger on every k-th step, or only counts
its contact changes computes the same landing. The kept
peaks and every other outcome are those of the full bookkeeping (up to how XLA compiles either
program); the sampled ledger residual is a maximum over fewer steps; a numerical failure is
still found, within k steps of where the every-step check finds it."""

import jax
import numpy as np
import pytest

import jaxland as jl
from jaxland._montecarlo._run import REPORTED_PEAKS

VEH = jl.paper_vehicle()
SCENE = jl.Scene(drop_height=0.0, sink_speed=2.4)  # reaches the secondary stage
T_END = 0.3
DT = 2e-5


def _summary(dt=DT, method="euler", t_end=T_END, **kw):
    solver = jl.Solver(dt=dt, t_end=t_end, save_dt=t_end, method=method, **kw).validate()
    return jax.device_get(jax.jit(lambda s: jl.landing(VEH, s, solver, "quarter"))(SCENE)[1])


@pytest.fixture(scope="module")
def full():
    return _summary()


def _assert_same(got, ref, keys):
    """Equal up to reassociation in the compiled program (measured: 2e-11 relative, on the
    accumulated slip): 1e-9 relative; the ledger residual, a difference of energies of ~1e3 J,
    to 1e-12 of the initial energy."""
    e_tol = 1e-12 * float(ref["energy_initial_J"])
    for k in keys:
        atol = {"energy_closure_max_J": e_tol,
                "ledger_error_rel": e_tol / float(ref["energy_dissipated_J"])}.get(k, 0.0)
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-9, atol=atol, err_msg=k)


def test_kept_peaks_are_those_of_the_full_bookkeeping(full):
    lean = _summary(peaks=("peak_body_accel_mps2",))
    dropped = {k for k in full if k.startswith("peak_")} - set(lean)
    assert dropped == {"peak_tangential_force_N", "peak_aux_force_N",
                       "peak_buffer_velocity_mps", "peak_foot_accel_mps2",
                       "peak_foot_accel_normal_mps2", "peak_foot_accel_tangential_mps2"}
    assert set(lean) == set(full) - dropped
    _assert_same(lean, full, lean)


def test_an_unknown_peak_is_refused_by_name():
    with pytest.raises(jl.ConfigError, match=r"solver\.peaks = 'peak_margin_deficit_m'.*quarter"):
        _summary(peaks=REPORTED_PEAKS["full"])
    with pytest.raises(jl.ConfigError, match=r"solver\.ledger_every"):
        jl.Solver(ledger_every=0).validate()
    with pytest.raises(jl.ConfigError, match=r"solver\.ledger_every = 5: needs a fixed-step"):
        jl.Solver(ledger_every=5, method="tsit5").validate()


def test_a_sampled_ledger_changes_only_the_residual(full):
    """Every 7th step (15000 steps: 2142 blocks and a remainder of 6): the landing itself is
    unchanged, the worst residual is taken over fewer steps, so it is at most the every-step
    one, and on a smooth ledger close to it."""
    lean = _summary(ledger_every=7)
    sampled = ("energy_closure_max_J", "ledger_error_rel")
    for k in sampled:
        assert 0.8 * full[k] <= lean[k] <= full[k] * (1 + 1e-9), (k, lean[k], full[k])
    _assert_same(lean, full, set(full) - set(sampled))
    assert int(lean["result"]) == int(jl.Result.SUCCESSFUL)


def test_a_sampled_ledger_still_finds_a_failure():
    """Explicit Euler at 1.3 x its stability limit blows up: with the ledger checked every 10th
    step the failure is found, at most 10 steps after the every-step check finds it."""
    dt = 1.3 * float(jl.stable_step(VEH))
    every = _summary(dt=dt, t_end=2000 * dt)
    sampled = _summary(dt=dt, t_end=2000 * dt, ledger_every=10)
    assert bool(every["failed"]) and bool(sampled["failed"])
    assert int(sampled["result"]) == int(every["result"])
    t0, t1 = float(every["failure_time_s"]), float(sampled["failure_time_s"])
    assert t0 <= t1 <= t0 + 10 * dt + 1e-12


def test_a_landing_without_an_event_log_counts_the_changes(full):
    lean = _summary(event_log=0)
    assert lean["event_times_s"].shape == (0,) and full["event_times_s"].shape == (256,)
    assert int(full["n_contact_changes"]) >= 2  # a touchdown, and a lift-off or more
    _assert_same(lean, full, set(full) - {"event_times_s"})
    with pytest.raises(jl.ConfigError, match=r"solver\.event_log = -1"):
        jl.Solver(event_log=-1).validate()


def test_time_loop_carry_starts_as_batched_as_the_landing():
    """``per_landing``: under vmap, a leaf is broadcast over the batch where the reference
    is batched (so the time loop's scans are batched in one round), and left alone where it is
    not; values and derivatives pass through unchanged."""
    import jax.numpy as jnp

    from jaxland._solvers._loop import per_landing

    x = {"peak": jnp.array(-jnp.inf), "log": jnp.zeros(3)}
    refs = jnp.array([1.0, 2.0])
    out = jax.vmap(lambda r: per_landing(x, r))(refs)
    assert out["peak"].shape == (2,) and out["log"].shape == (2, 3)
    np.testing.assert_array_equal(out["log"], 0.0)
    with pytest.raises(ValueError):  # batched: cannot be returned unmapped
        jax.vmap(lambda r: per_landing(x, r), out_axes=None)(refs)
    # an unbatched reference leaves the leaf unbatched
    same = jax.vmap(lambda r: per_landing(x, 1.0) ["log"] + 0 * r, out_axes=0)(refs)
    np.testing.assert_array_equal(same, 0.0)
    jax.vmap(lambda r: per_landing(x, 1.0), out_axes=None)(refs)
    # derivatives of the leaf pass through; the reference gets none
    g = jax.grad(lambda a, r: jnp.sum(per_landing(3.0 * a, r)), argnums=(0, 1))(2.0, 5.0)
    assert g == (3.0, 0.0)
    gv = jax.vmap(jax.grad(lambda a, r: per_landing(a * a, r)))(refs, refs)
    np.testing.assert_array_equal(gv, 2.0 * refs)


@pytest.mark.parametrize("method", ["euler", "leapfrog", "impulse", "tsit5"])
def test_a_landing_without_a_trajectory_has_the_same_summary(method):
    """``Solver(trajectory=False)`` (a Monte Carlo's) saves nothing and changes no bit of the
    summary: the saved state's evaluation is dead code XLA removes either way."""
    def run(**kw):
        solver = jl.Solver(dt=DT, t_end=T_END, save_dt=T_END, method=method, **kw).validate()
        return jax.device_get(jax.jit(lambda s: jl.landing(VEH, s, solver, "quarter"))(SCENE))
    (traj, ref), (none, got) = run(), run(trajectory=False)
    assert none == {} and traj
    assert ref.keys() == got.keys()
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)
    with pytest.raises(jl.ConfigError, match=r"solver\.trajectory"):
        jl.Solver(trajectory=1).validate()
