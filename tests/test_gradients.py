"""Differentiability: grad, jacfwd, vmap(grad) and grad(vmap) of a stroke/force trace loss, against
central finite differences; no NaN gradients over the documented drop-height envelope.

Where AD and FD agree: on the first impact (foot in continuous contact), for D_b, k_b1, F1, F2
to <= 3e-5 relative (h = 1e-6). k and gamma are kinked there at ~1e-6 relative spacing: FD
converges to AD only for h ~ 1e-7. Where they do not: on records that include lift-off and
re-contact (the paper's drop after ~0.37 s) the discrete map has dense kinks (contact on/off at
step boundaries) and the loss is exact-but-jagged below ~1e-5 relative parameter change, so FD
secants and the AD slope of the local smooth piece differ for every parameter (a 1-D scan of
the loss in D_b at 1e-7 steps showed local slopes varying by over an order of magnitude, and
not around the AD slope). Curing that is the integrators issue's work.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxland as jl

VEH = jl.paper_vehicle()
NAMES = ("D_b", "k_b1", "F1", "F2", "k", "gamma")
V_TD = float(jl.Scene().touchdown_speed(float(VEH.g)))
SOLVER = jl.Solver(dt=1e-5, t_end=0.15, save_dt=1e-4)  # first impact, from touchdown


def _params(v):
    return (v.leg.D_b, v.honeycomb.k_b1, v.honeycomb.F1, v.honeycomb.F2, v.ground.k,
            v.ground.gamma)


def _vehicle(theta):
    """Paper vehicle with the six parameters scaled by exp(theta) (log-space, as a fit is)."""
    new = tuple(p * jnp.exp(t) for p, t in zip(_params(VEH), theta))
    return eqx.tree_at(_params, VEH, new)


def _trace_loss(theta, scene, ref):
    tr, _ = jl.landing(_vehicle(theta), scene, SOLVER, "quarter")
    return (jnp.mean((tr["stroke_m"] - ref["stroke_m"]) ** 2) / 1e-3**2
            + jnp.mean((tr["strut_force_N"] - ref["strut_force_N"]) ** 2) / 1e3**2)


@pytest.fixture(scope="module")
def setup():
    scene = jl.Scene.from_touchdown_speed(V_TD)
    ref, _ = jax.jit(lambda th: jl.landing(_vehicle(th), scene, SOLVER))(jnp.full(6, 0.05))
    loss = jax.jit(lambda th: _trace_loss(th, scene, ref))
    return scene, ref, loss


@pytest.fixture(scope="module")
def trace_grad():
    """grad of the trace loss in theta, (theta, scene, ref) -> (6,): compiled once, shared by
    the tests below (the scene and the reference are arguments, not constants)."""
    return jax.jit(jax.grad(_trace_loss))


def _fd(loss, i, h):
    e = jnp.zeros(6).at[i].set(h)
    return (float(loss(e)) - float(loss(-e))) / (2 * h)


def test_grad_and_jacfwd_match_central_differences(setup, trace_grad):
    """D_b, k_b1, F1, F2: AD = central FD to 1e-4 (h = 1e-6, measured agreement <= 3e-5)."""
    scene, ref, loss = setup
    th0 = jnp.zeros(6)
    g_rev = trace_grad(th0, scene, ref)
    g_fwd = jax.jit(jax.jacfwd(_trace_loss))(th0, scene, ref)
    np.testing.assert_allclose(g_rev, g_fwd, rtol=1e-9)
    for i, name in enumerate(NAMES[:4]):
        fd = _fd(loss, i, 1e-6)
        assert abs(float(g_rev[i]) - fd) <= 1e-4 * abs(fd), (name, float(g_rev[i]), fd)


def test_k_and_gamma_are_exact_but_kinked(setup, trace_grad):
    """k and gamma: even in the first impact the discrete map has kinks ~1e-6 apart in relative
    parameter (contact and stick/slip switches landing on step boundaries), so FD secants at
    h = 1e-5 miss the AD slope by ~1 %; they converge to it as h shrinks (<= 2e-4 at h = 1e-7).
    AD is the exact derivative of the local smooth piece; smoothing is the integrators issue."""
    scene, ref, loss = setup
    g = trace_grad(jnp.zeros(6), scene, ref)
    for i in (4, 5):
        errs = [abs(_fd(loss, i, h) - float(g[i])) / abs(float(g[i])) for h in (1e-5, 1e-7)]
        assert errs[1] < 1e-3, (NAMES[i], errs)
        assert errs[1] < errs[0], (NAMES[i], errs)


def test_vmap_of_grad_equals_grad_per_scene_and_grad_of_vmap(setup, trace_grad):
    _, ref, _ = setup
    speeds = jnp.array([1.6, 2.0, 2.4])
    scenes = jl.Scene.batch(drop_height=0.0, sink_speed=speeds)
    # not weak-typed, as the other tests' theta: trace_grad is then not compiled a second time
    th0 = jnp.full(6, 0.01, dtype=jnp.float64)
    gfun = jax.grad(_trace_loss)
    axes = jl.batch_axes(scenes)
    batched = jax.jit(jax.vmap(gfun, in_axes=(None, axes, None)))(th0, scenes, ref)
    for i, v in enumerate(speeds):
        one = trace_grad(th0, jl.Scene.from_touchdown_speed(v), ref)
        np.testing.assert_allclose(batched[i], one, rtol=1e-10)
    summed = jax.jit(jax.grad(lambda th: jnp.sum(
        jax.vmap(_trace_loss, in_axes=(None, axes, None))(th, scenes, ref))))(th0)
    np.testing.assert_allclose(summed, jnp.sum(batched, axis=0), rtol=1e-10)


def test_no_nan_gradients_over_the_drop_height_envelope():
    """Drops of 0.05-0.5 m over 0.6 s (free fall, impact, lift-off, re-contact): every gradient of
    max stroke, peak forces and the final stroke is finite."""
    heights = jnp.linspace(0.05, 0.5, 10)
    solver = jl.Solver(dt=1e-5, t_end=0.6, save_dt=1e-3)

    def outcome(theta, h):
        _, s = jl.landing(_vehicle(theta), jl.Scene(drop_height=h), solver, "quarter")
        return (s["max_stroke_m"] * 1e3 + s["final_stroke_m"] * 1e3
                + s["peak_normal_force_N"] * 1e-3 + s["peak_strut_force_N"] * 1e-3)

    grads = jax.jit(jax.vmap(jax.grad(outcome), in_axes=(None, 0)))(jnp.zeros(6), heights)
    assert grads.shape == (10, 6)
    assert bool(jnp.all(jnp.isfinite(grads)))
    assert bool(jnp.all(jnp.abs(grads[:, 2]) > 0))  # F1 always matters
