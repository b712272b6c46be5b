"""Unit tests of the pure force laws, each against an independent expectation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxland as jl
from jaxland import laws

VEH = jl.paper_vehicle()
HC = VEH.honeycomb
GR = VEH.ground


def _x(*vals):
    return jnp.asarray(vals, dtype=jnp.float64)


# --------------------------------------------------------------------------------- honeycomb

def test_virgin_curve_matches_paper_piecewise_law():
    """Paper section 2.3 with k_b2 = k_b4 = 0: F = k_b1 x, F1, F1 + k_b3 (x - x_L2), F2."""
    x1, x2, x3, x4 = (float(v) for v in (HC.x_L1, HC.x_L2, HC.x_L3, HC.x_L4))
    F1, F2, k1, k3 = (float(v) for v in (HC.F1, HC.F2, HC.k_b1, HC.k_b3))
    xs = np.linspace(0.0, x4 * 0.999, 4001)
    expected = np.where(xs < x1, k1 * xs, np.where(xs < x2, F1, np.where(
        xs < x3, F1 + k3 * (xs - x2), F2)))
    got = jax.vmap(lambda x: laws.honeycomb_virgin_force(x, HC))(jnp.asarray(xs))
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-6)
    # monotone virgin loading returns the same curve through the memory path
    out = jax.vmap(lambda x: laws.honeycomb(x, x, HC).force)(jnp.asarray(xs))
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-6)


@pytest.mark.parametrize("x_max_mm", [0.3, 20.0, 57.9, 58.0, 70.0, 150.0, 190.0])
def test_absorbed_energy_is_integral_of_force(x_max_mm):
    """Work of the virgin curve up to x_max = stored elastic + crush dissipation (closed forms)."""
    x_max = x_max_mm * 1e-3
    xs = np.linspace(0.0, x_max, 200001)
    f = np.asarray(jax.vmap(lambda x: laws.honeycomb_virgin_force(x, HC))(jnp.asarray(xs)))
    work = np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(xs))
    out = laws.honeycomb(_x(x_max)[0], _x(x_max)[0], HC)
    np.testing.assert_allclose(float(out.elastic_energy + out.crush_energy), work, rtol=1e-6)


@pytest.mark.parametrize("x_max_mm", [30.0, 58.0, 80.0])
def test_unload_reload_is_elastic_and_stores_what_it_returns(x_max_mm):
    """Below x_max: same force on unloading and reloading, dW/dx = F, no tension, no new crush."""
    x_max = x_max_mm * 1e-3
    xs = jnp.linspace(x_max, x_max - 5e-3, 20001)
    out = jax.vmap(lambda x: laws.honeycomb(x, x_max, HC))(xs)
    back = jax.vmap(lambda x: laws.honeycomb(x, x_max, HC))(xs[::-1])
    np.testing.assert_allclose(out.force[::-1], back.force)
    assert np.all(np.asarray(out.force) >= 0.0)
    assert np.all(np.asarray(out.x_max) == x_max)
    np.testing.assert_allclose(out.crush_energy, out.crush_energy[0])
    # elastic energy released = integral of force over the unloading path
    f = np.asarray(out.force)
    released = np.sum(0.5 * (f[1:] + f[:-1]) * -np.diff(np.asarray(xs)))
    np.testing.assert_allclose(float(out.elastic_energy[0] - out.elastic_energy[-1]), released,
                               rtol=1e-6, atol=1e-9)
    # the first unloading slope is the stage's elastic stiffness
    slope = (float(out.force[0]) - float(out.force[1])) / float(xs[0] - xs[1])
    expected = float(HC.k_b3) if x_max > float(HC.x_L2) else float(HC.k_b1)
    np.testing.assert_allclose(slope, expected, rtol=1e-6)


def test_honeycomb_never_pulls_unless_bonded():
    x_max = 0.03
    xs = jnp.linspace(-0.02, x_max, 101)
    free = jax.vmap(lambda x: laws.honeycomb(x, x_max, HC).force)(xs)
    assert float(jnp.min(free)) == 0.0
    bonded = HC.__class__(**{**{f: getattr(HC, f) for f in
                               ("k_b1", "F1", "x_L2", "k_b3", "F2", "x_L4", "k_bottom")},
                             "bonded": True})
    pulled = jax.vmap(lambda x: laws.honeycomb(x, x_max, bonded).force)(xs)
    assert float(jnp.min(pulled)) < 0.0


def test_bottoming_out_is_stiff_and_elastic():
    x4 = float(HC.x_L4)
    out = laws.honeycomb(_x(x4 + 1e-3)[0], _x(0.0)[0], HC)
    np.testing.assert_allclose(float(out.force), float(HC.F2) + float(HC.k_bottom) * 1e-3)


def test_wierzbicki_formula():
    """sigma_m = 6.6 sigma_0 (t/D)^(5/3) on a 98 mm circle (Wierzbicki 1983), by hand."""
    s0, t, d, dia = 300e6, 0.07e-3, 8.66e-3, 0.098
    expected = 6.6 * s0 * (t / d) ** (5 / 3) * np.pi * dia**2 / 4
    np.testing.assert_allclose(float(jl.plateau_force(d, t, dia, s0)), expected, rtol=1e-12)


# --------------------------------------------------------------------------- strut and aux

def test_structural_damping_law_and_power():
    F_bh, D_b = 5000.0, 1.5
    for v_b in (-2.0, -0.5, 0.0, 0.4, 0.9):
        out = laws.strut_force(F_bh, 0.01, v_b, D_b, 1e7)
        expected = F_bh * max(1.0 + D_b * v_b, 0.0)  # F_bh + D_b v_b F_bh, never pulling
        np.testing.assert_allclose(float(out.force), expected)
        assert float(out.damping_power) >= 0.0
    # a bonded honeycomb in tension is damped on |F_bh|: the damping never feeds energy in
    for v_b in (-2.0, -0.5, 0.5, 2.0):
        out = laws.strut_force(-2000.0, 0.01, v_b, D_b, 1e7)
        np.testing.assert_allclose(float(out.force), -2000.0 + D_b * v_b * 2000.0)
        assert float(out.damping_power) >= 0.0
    top = laws.strut_force(0.0, -1e-3, 0.0, D_b, 1e7)
    np.testing.assert_allclose(float(top.force), -1e4)
    np.testing.assert_allclose(float(top.topout_energy), 0.5 * 1e7 * 1e-6)


def test_aux_strut_spring():
    out = laws.aux_strut(1.99, 2.0, 5e6)
    np.testing.assert_allclose(float(out.force), 5e4)
    np.testing.assert_allclose(float(out.elastic_energy), 0.5 * 5e6 * 1e-4)


# ------------------------------------------------------------------------------- normal contact

def test_normal_contact_bi_stiffness_and_pit():
    k, gamma = float(GR.k), float(GR.gamma)
    d_max = 2e-3
    load = laws.normal_contact(d_max, 0.0, 0.0, GR)
    np.testing.assert_allclose(float(load.spring_force), k * d_max)  # compression: k
    d = 1.5e-3
    unload = laws.normal_contact(d, 0.0, d_max, GR)
    np.testing.assert_allclose(float(unload.spring_force), k / (1 - gamma) * (d - gamma * d_max))
    np.testing.assert_allclose(float(unload.pit_depth), gamma * d_max)
    above = laws.normal_contact(gamma * d_max * 0.99, 0.0, d_max, GR)
    assert float(above.force) == 0.0
    # elastic energy at the deepest point = (1 - gamma) of the work done in compression
    np.testing.assert_allclose(float(load.elastic_energy), (1 - gamma) * 0.5 * k * d_max**2)
    np.testing.assert_allclose(float(load.plastic_energy), gamma * 0.5 * k * d_max**2)


def test_normal_contact_damping_factor():
    chi = float(GR.chi)
    out = laws.normal_contact(1e-3, 2.0, 0.0, GR)
    np.testing.assert_allclose(float(out.force), float(out.spring_force) * (1 + chi * 2.0))
    assert float(out.damping_power) > 0.0
    out = laws.normal_contact(1e-3, -2.0, 1e-3, GR)
    assert float(out.damping_power) > 0.0


def _bounce(gamma, v0=2.0, m=1.0, k=2e6, dt=2e-8):
    """A free mass (no gravity) hitting the bi-stiffness ground: rebound speed and pit."""
    ground = jl.Ground(k=k, gamma=gamma, chi=0.0, mu=0.0, k_tan=1.0)
    n = int(4.0 * np.pi * np.sqrt(m / k) / dt)

    def step(c, _):
        z, v, d_max = c
        out = laws.normal_contact(-z, -v, d_max, ground)
        v = v + dt * out.force / m
        return (z + dt * v, v, out.d_max), None

    (z, v, d_max), _ = jax.lax.scan(step, (0.0, -v0, 0.0), None, length=n)
    return float(v), float(d_max), float(ground.gamma) * float(d_max)


@pytest.mark.parametrize("gamma", [0.0, 0.3, 0.5, 0.8])
def test_single_mass_rebound_matches_closed_form(gamma):
    """Closed form: d_max = v0 sqrt(m/k), rebound speed sqrt(1 - gamma) v0, pit gamma d_max."""
    v0, m, k = 2.0, 1.0, 2e6
    v_out, d_max, pit = _bounce(gamma, v0, m, k)
    np.testing.assert_allclose(d_max, v0 * np.sqrt(m / k), rtol=1e-4)
    np.testing.assert_allclose(v_out, np.sqrt(1 - gamma) * v0, rtol=1e-4)
    np.testing.assert_allclose(pit, gamma * v0 * np.sqrt(m / k), rtol=1e-4)


# --------------------------------------------------------------------------- tangential contact

def test_tangential_stick_and_slip_3d():
    k_tan, mu = float(GR.k_tan), float(GR.mu)
    N = 1000.0
    anchor = (0.0, 0.0)
    small = np.array([1e-3, 2e-3])  # |F| = 157 N < mu N = 500 N: stick
    out = laws.tangential_contact(tuple(small), anchor, N, GR)
    np.testing.assert_allclose(np.array(out.force), -k_tan * small)
    assert not bool(out.slipping) and float(out.slip) == 0.0
    big = np.array([0.03, -0.04])  # |u| = 0.05, k|u| = 3500 N > 500 N: slip
    out = laws.tangential_contact(tuple(big), anchor, N, GR)
    f = np.array(out.force)
    np.testing.assert_allclose(np.linalg.norm(f), mu * N, rtol=1e-12)
    np.testing.assert_allclose(f / np.linalg.norm(f), -big / 0.05, rtol=1e-12)
    assert bool(out.slipping)
    np.testing.assert_allclose(float(out.slip), 0.05 - mu * N / k_tan, rtol=1e-12)
    np.testing.assert_allclose(float(out.slip_energy), mu * N * float(out.slip), rtol=1e-12)
    air = laws.tangential_contact(tuple(big), anchor, 0.0, GR)
    np.testing.assert_allclose(np.array(air.force), 0.0)
    np.testing.assert_allclose(np.array(air.anchor), big)  # off the ground it follows the foot
    assert float(air.slip) == 0.0 and not bool(air.slipping)  # ...and that is not slip


# ---------------------------------------------------------------------------- gradient safety

@pytest.mark.parametrize("x,x_max", [(0.0, 0.0), (0.47e-3, 0.47e-3), (57.6e-3, 57.6e-3),
                                     (0.0, 0.03), (-1e-3, 0.0), (0.1834, 0.1834)])
def test_honeycomb_gradients_finite_at_breakpoints(x, x_max):
    def f(x, x_max, hc):
        out = laws.honeycomb(x, x_max, hc)
        return out.force + out.elastic_energy + out.crush_energy

    g = jax.grad(f, argnums=(0, 1, 2))(_x(x)[0], _x(x_max)[0], HC)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(g))


@pytest.mark.parametrize("d,d_max", [(0.0, 0.0), (-1e-3, 0.0), (1e-3, 2e-3), (1e-3, 1e-3)])
def test_contact_gradients_finite_at_zero_and_boundaries(d, d_max):
    def f(d, d_max, foot, gr):
        n = laws.normal_contact(d, 0.1, d_max, gr)
        t = laws.tangential_contact((foot[0], foot[1]), (0.0, 0.0), n.force, gr)
        return n.force + n.elastic_energy + t.force[0] + t.force[1] + t.elastic_energy \
            + t.slip_energy

    for foot in (_x(0.0, 0.0), _x(1e-3, 0.0), _x(0.5, 0.2)):
        g = jax.grad(f, argnums=(0, 1, 2, 3))(_x(d)[0], _x(d_max)[0], foot, GR)
        assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(g))


@pytest.mark.parametrize("stretch", [0.0, 1e-3])
def test_tangential_force_without_normal_force_has_no_derivative(stretch):
    """Without a normal force the tangential force is 0 for every stretch, so its derivative
    by the foot's position is 0, also at zero stretch (a foot in the air that does not move
    sideways), and the anchor follows the foot (derivative 1); with a normal force and zero
    stretch the foot sticks on a spring of k_tan."""
    def force_and_anchor(x, normal):
        out = laws.tangential_contact((x, 0.0), (0.0, 0.0), normal, GR)
        return jnp.stack([out.force[0], out.anchor[0]])

    air = np.asarray(jax.jacfwd(force_and_anchor)(stretch, 0.0))
    np.testing.assert_array_equal(air, [0.0, 1.0])
    np.testing.assert_array_equal(np.asarray(jax.jacrev(force_and_anchor)(stretch, 0.0)),
                                  [0.0, 1.0])
    stuck = np.asarray(jax.jacfwd(force_and_anchor)(0.0, 1000.0))
    np.testing.assert_array_equal(stuck, [-float(GR.k_tan), 0.0])
