"""The honeycomb's optional initial crush peak and secondary unloading stiffness (issue 12).

Each test checks the law against something computed independently of it: a hand-written numpy
virgin curve, the work integral of the force along a load/unload/reload path, the paper's law
(stored hashes of results computed before the extensions existed), central finite differences.
"""

import dataclasses
import hashlib
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxland as jl
from jaxland import laws

VEH = jl.paper_vehicle()
HC0 = VEH.honeycomb
F1, F2 = float(HC0.F1), float(HC0.F2)
K1, K3 = float(HC0.k_b1), float(HC0.k_b3)
X1, X2, X3, X4 = (float(HC0.x_L1), float(HC0.x_L2), float(HC0.x_L3), float(HC0.x_L4))
_NONE = dict(is_leaf=lambda x: x is None)


def _hc(r1=None, r2=None, rho=None, L1=2e-3, L2=2e-3, bonded=False):
    """The paper honeycomb with the extensions set (None: off)."""
    def f64(x):
        return None if x is None else jnp.float64(x)

    hc = eqx.tree_at(lambda h: (h.peak_ratio1, h.peak_ratio2, h.unload_ratio, h.peak_length1,
                                h.peak_length2), HC0,
                     (f64(r1), f64(r2), f64(rho), f64(L1), f64(L2)), **_NONE)
    return dataclasses.replace(hc, bonded=True) if bonded else hc


def _path(*stops, n=100_001):
    """Strokes along straight segments between the stops [m] (a load/unload history)."""
    return np.concatenate([np.linspace(a, b, n)[:-1] for a, b in zip(stops[:-1], stops[1:])]
                          + [[stops[-1]]])


def _run(hc, xs, w=0.0):
    """The law along a stroke history with its memory carried (as a time loop does)."""
    def step(x_max, x):
        o = laws.honeycomb(x, x_max, hc, w)
        return o.x_max, (o.force, o.elastic_energy, o.crush_energy, o.plastic_set)

    _, out = jax.lax.scan(step, jnp.float64(0.0), jnp.asarray(xs))
    return [np.asarray(a) for a in out]

def _assert_ledger_closes(hc, xs):
    """Along the stroke path ``xs``: the work of the force (trapezoid) equals elastic + crush
    energy (closed forms), crush never decreases and the plastic set never shrinks. Returns
    the force, elastic and crush energy and plastic set along the path."""
    f, el, cr, ps = _run(hc, xs)
    work = np.cumsum(np.concatenate([[0.0], 0.5 * (f[1:] + f[:-1]) * np.diff(xs)]))
    scale = el[-1] + cr[-1]
    np.testing.assert_allclose(work, el + cr, rtol=0, atol=2e-9 * scale)
    assert np.all(np.diff(cr) >= -1e-9 * scale)
    assert np.all(np.diff(ps) >= -1e-15)
    return f, el, cr, ps



def _hash(arrays):
    m = hashlib.sha256()
    for a in arrays:
        m.update(np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes())
    return m.hexdigest()[:16]


# --------------------------------------------------------------------------- default unchanged

# sha256 prefixes computed at commit b261030, before the extensions existed (same grids, same
# calls): the paper's law must stay bit for bit the same with the extensions off.
LAW_REF = {0.0: "fd048cb2935573e0", 1e-6: "2ec206647b3aeb55", 1e-4: "3aab50fa589588ea"}


@pytest.mark.parametrize("w", sorted(LAW_REF))
def test_default_law_is_bit_for_bit_the_paper_law(w):
    hc = jl.paper_vehicle().honeycomb
    assert hc.peak_ratio1 is None and hc.peak_ratio2 is None and hc.unload_ratio is None
    xs = jnp.linspace(-0.01, 0.19, 2001)
    xm = jnp.linspace(0.0, 0.19, 39)
    for law in (laws.honeycomb, _paper_law_b261030):
        out = jax.vmap(lambda m: jax.vmap(lambda x: law(x, m, hc, w))(xs))(xm)
        assert _hash([out.force, out.x_max, out.elastic_energy, out.crush_energy,
                      out.plastic_set]) == LAW_REF[w]


def _paper_law_b261030(x, x_max_prev, hc, smooth=0.0):
    """The honeycomb law exactly as it was at commit b261030 (frozen copy, for the landings)."""
    from jaxland._laws._smooth import ramp  # noqa: PLC0415

    def clip(v, lo, hi):
        return jnp.minimum(jnp.maximum(v, lo), hi)

    def stack(y1, y2, y3, yt, p1, p2, x_max):
        force = hc.k_b1 * y1 + hc.k_b3 * y2 + hc.k_bottom * y3
        elastic = (0.5 * hc.k_b1 * y1**2 + hc.F1 * y2 + 0.5 * hc.k_b3 * y2**2
                   + hc.F2 * y3 + 0.5 * hc.k_bottom * y3**2)
        if hc.bonded:
            force = force + hc.k_b1 * yt
            elastic = elastic + 0.5 * hc.k_b1 * yt**2
        return laws.HoneycombOut(force, x_max, elastic, hc.F1 * p1 + hc.F2 * p2, p1 + p2)

    hc = hc.curve() if isinstance(hc, jl.Honeycomb) else hc
    w = smooth
    if w != 0.0:
        x_max = x_max_prev + ramp(x - x_max_prev, w)
        p1 = ramp(x_max - hc.x_L1, w) - ramp(x_max - hc.x_L2, w)
        p2 = ramp(x_max - hc.x_L3, w) - ramp(x_max - hc.x_L4, w)
        y = x - (p1 + p2)
        y_2 = hc.x_L1 + hc.x_L3 - hc.x_L2
        r0, r1, r2 = ramp(y, w), ramp(y - hc.x_L1, w), ramp(y - y_2, w)
        return stack(r0 - r1, r1 - r2, r2, y - r0, p1, p2, x_max)
    x_max = jnp.maximum(x_max_prev, x)
    p1 = clip(x_max - hc.x_L1, 0.0, hc.x_L2 - hc.x_L1)
    p2 = clip(x_max - hc.x_L3, 0.0, hc.x_L4 - hc.x_L3)
    y = x - (p1 + p2)
    dy3 = hc.x_L3 - hc.x_L2
    return stack(clip(y, 0.0, hc.x_L1), clip(y - hc.x_L1, 0.0, dy3),
                 jnp.maximum(y - hc.x_L1 - dy3, 0.0), jnp.minimum(y, 0.0), p1, p2, x_max)


LANDINGS = {
    "paper": lambda: jl.simulate(t_end=0.5),
    "verlet_smooth": lambda: jl.simulate(t_end=0.5, method="verlet", smoothing_m=1e-6,
                                         smoothing_N=10.0),
    "h0.6_secondary": lambda: jl.simulate(jl.Scene(drop_height=0.6), t_end=0.5),
    "full_3d_tilted": lambda: jl.simulate(jl.Scene(pitch=0.07), t_end=0.3),
}


@pytest.mark.parametrize("case", sorted(LANDINGS))
def test_default_landings_are_bit_for_bit_those_of_the_paper_law(case):
    """Whole landings, jitted, with the default vehicle against the same landings with the
    models' honeycomb law swapped for the frozen b261030 copy (XLA contracts multiply-adds
    into FMAs, so only an unchanged expression graph gives the same bits: even exact "+ 0.0"
    terms would not). The paper drop, a smoothed Verlet run, a 0.6 m drop into the secondary
    stage and a tilted 3-D landing."""
    run = LANDINGS[case]
    targets = [m for name, m in list(sys.modules.items()) if name.startswith("jaxland")
               and getattr(m, "honeycomb", None) is laws.honeycomb and m is not laws]
    assert len(targets) >= 2, "the quarter and the full model must both use laws.honeycomb"
    jax.clear_caches()
    now = run()
    try:
        for m in targets:
            m.honeycomb = _paper_law_b261030
        jax.clear_caches()
        ref = run()
    finally:
        for m in targets:
            m.honeycomb = laws.honeycomb
        jax.clear_caches()
    assert _hash([now.trajectory[c] for c in sorted(now.trajectory)]) == \
        _hash([ref.trajectory[c] for c in sorted(ref.trajectory)])


def test_toml_off_values_give_the_paper_law_and_round_trip(tmp_path):
    """The TOML 'off' values (ratio 1) map to None; a peak given in TOML survives a round trip."""
    veh = jl.vehicle_from_dict({"honeycomb": {"peak_ratio1": 1.0, "unload_ratio": 1.0}})
    assert veh.honeycomb.peak_ratio1 is None and veh.honeycomb.unload_ratio is None
    on = jl.vehicle_from_dict({"honeycomb": {"peak_ratio1": 1.25, "peak_length1_mm": 3.0,
                                             "unload_ratio": 1.2}})
    assert float(on.honeycomb.peak_ratio1) == 1.25 and float(on.honeycomb.peak_length1) == 3e-3
    (tmp_path / "v.toml").write_text(jl.vehicle_to_toml(on))
    back = jl.load_vehicle(tmp_path / "v.toml")
    for name in ("peak_ratio1", "peak_length1", "unload_ratio"):
        assert float(getattr(back.honeycomb, name)) == float(getattr(on.honeycomb, name))
    assert back.honeycomb.peak_ratio2 is None


def test_general_law_with_neutral_values_is_the_paper_law():
    """Extensions switched on at their neutral values (ratio 1) take the general code path and
    must give the paper's law (to round-off), hard and smoothed."""
    xs = _path(0.0, 0.01, 0.004, 0.07, 0.06, 0.19, n=20_001)
    for w in (0.0, 1e-5):
        ref = _run(HC0, xs, w)
        got = _run(_hc(1.0, 1.0, 1.0), xs, w)
        for a, b in zip(ref, got):
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-9)


# ------------------------------------------------------------------------------- the peak law

def _expected_virgin(x, r1, L1, r2, L2):
    """Hand-written virgin curve: elastic rise to the peak r F, linear fall to the plateau over
    L, plateau; the secondary likewise from x_L2 on; bottoming past x_L4."""
    a1, a2 = (r1 - 1) * F1, (r2 - 1) * F2
    xp1, xp2 = X1 + a1 / K1, X3 + a2 / K3
    f = np.where(x < xp1, K1 * x, F1 + a1 * np.clip(1 - (x - xp1) / L1, 0, 1))
    f = np.where(x < X2, f, np.where(x < xp2, F1 + K3 * (x - X2),
                                     F2 + a2 * np.clip(1 - (x - xp2) / L2, 0, 1)))
    return f + 1e8 * np.maximum(x - X4, 0.0)


@pytest.mark.parametrize("r1,L1,r2,L2", [(1.3, 2e-3, 1.2, 2e-3), (1.8, 10e-3, 1.0, 2e-3),
                                         (1.0, 2e-3, 1.5, 5e-3)])
def test_virgin_curve_rises_to_the_peak_and_falls_linearly_to_the_plateau(r1, L1, r2, L2):
    hc = _hc(r1, r2, None, L1, L2)
    xs = np.linspace(0.0, X4 * 1.001, 40_001)
    expected = _expected_virgin(xs, r1, L1, r2, L2)
    closed = jax.vmap(lambda x: laws.honeycomb_virgin_force(x, hc))(jnp.asarray(xs))
    np.testing.assert_allclose(closed, expected, rtol=1e-11, atol=1e-6)
    memory = jax.vmap(lambda x: laws.honeycomb(x, x, hc).force)(jnp.asarray(xs))
    np.testing.assert_allclose(memory, expected, rtol=1e-11, atol=1e-6)
    xp1 = X1 + (r1 - 1) * F1 / K1  # the peak itself is r1 F1
    assert float(laws.honeycomb_virgin_force(xp1, hc)) == pytest.approx(r1 * F1, rel=1e-12)


@pytest.mark.parametrize("w", [0.0, 1e-6])
def test_peak_only_on_virgin_material(w):
    """A block crushed past its peak and reloaded reaches only the plateau (no second peak); one
    unloaded in mid-decay reloads to the strength it had left, then keeps decaying."""
    r1, L1 = 1.5, 8e-3
    hc = _hc(r1, 1.4, None, L1, 6e-3)
    xp1 = X1 + (r1 - 1) * F1 / K1
    # crushed past the peak, unloaded to zero force, reloaded well past the old maximum
    x_m = xp1 + L1 + 5e-3
    f, *_ = _run(hc, _path(0.0, x_m, 0.0, x_m + 10e-3), w)
    tol = 2.0 * K1 * w + 1e-6  # the smoothed law is exact outside its bands of width w
    reload = f[2 * 100_000:]
    assert np.max(reload) <= F1 * (1 + 1e-9) + tol
    assert np.max(f[:100_000]) >= r1 * F1 * (1 - 5e-4)  # the virgin loading had its peak
    # unloaded in mid-decay: reloads to what was left, S(x_m) = F1 + a (1 - s / L)
    x_m = xp1 + 0.5 * L1
    f, *_ = _run(hc, _path(0.0, x_m, x_m - 1e-3, x_m + L1), w)
    left = F1 + (r1 - 1) * F1 * 0.5
    back = f[100_000:]
    assert np.max(back) <= left + tol
    np.testing.assert_allclose(f[-1], F1, atol=tol)
    # the same for the secondary stage's peak: crushed past it, unloaded, reloaded
    xp2 = X3 + 0.4 * F2 / K3
    x_m = xp2 + 6e-3 + 2e-3
    f, *_ = _run(hc, _path(0.0, x_m, x_m - 2e-3, x_m + 5e-3), w)
    assert np.max(f[:100_000]) >= 1.4 * F2 * (1 - 5e-4)
    assert np.max(f[100_000:]) <= F2 + tol


CASES = {
    "peaks": dict(r1=1.3, r2=1.2),
    "bare_peaks_long": dict(r1=1.8, r2=1.5, L1=10e-3, L2=8e-3),
    "unloading": dict(rho=1.5),
    "both_bonded": dict(r1=1.3, r2=1.2, rho=1.3, bonded=True),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_work_of_the_force_is_stored_plus_crushed_along_any_history(case):
    """Energy ledger exact: integral F dx along load / unload / reload cycles through both
    stages equals the change of elastic + crush energy (closed forms), crush never decreases,
    and fully unloaded (no pull) the work left is crush only."""
    hc = _hc(**CASES[case])
    xs = _path(0.0, 0.003, 0.0005, 0.009, -0.002 if CASES[case].get("bonded") else 0.001,
               0.065, 0.061, 0.0715, 0.07, 0.12)
    _assert_ledger_closes(hc, xs)


def test_unloading_ratio_sets_the_recovery_after_the_secondary_stage():
    """rho = k_b1 / k_b3 unloads the whole crushed stack along k_b1 (single stiffness); rho = 1
    retraces k_b3 down to F1, then k_b1. Recovery to zero force: F / (rho k_b3) + ... ."""
    x_m = 0.1  # on the secondary plateau
    for rho, expected in ((None, (F2 - F1) / K3 + F1 / K1), (K1 / K3, F2 / K1),
                          (1.3, (F2 - F1) / (1.3 * K3) + F1 / K1)):
        f, *_ = _run(_hc(rho=rho), _path(0.0, x_m, x_m - 3e-3, n=300_001))
        x = _path(0.0, x_m, x_m - 3e-3, n=300_001)
        i = np.argmax(np.arange(len(f)) > 300_000)
        zero = x[i:][np.argmax(f[i:] <= 0.0)]
        np.testing.assert_allclose(x_m - zero, expected, rtol=1e-4)
        # it starts from the secondary plateau, and its first slope is rho k_b3
        np.testing.assert_allclose(f[i - 1], F2, rtol=1e-9)
        slope = (f[i - 1] - f[i + 10]) / (x[i - 1] - x[i + 10])
        np.testing.assert_allclose(slope, (1.0 if rho is None else rho) * K3, rtol=1e-6)


# ------------------------------------------------------------------------------- gradients

PNAMES = ("peak_ratio1", "peak_length1", "peak_ratio2", "unload_ratio", "F1", "k_b1")


def _law_sum(theta, x, x_max, w):
    hc = _hc(1.3, 1.2, 1.3)
    vals = tuple(getattr(hc, n) * jnp.exp(t) for n, t in zip(PNAMES, theta))
    hc = eqx.tree_at(lambda h: tuple(getattr(h, n) for n in PNAMES), hc, vals)
    o = laws.honeycomb(x, x_max, hc, w)
    return o.force / 1e3 + o.elastic_energy + o.crush_energy + o.plastic_set * 1e3


@pytest.mark.parametrize("x,x_max,w", [
    (X1 + 0.35 * F1 / K1, X1 + 0.3 * F1 / K1 + 1e-3, 0.0),  # reloading in mid-decay
    (0.004, 0.005, 0.0),  # unloaded after the peak
    (X3 + 0.25 * F2 / K3, X3 + 0.2 * F2 / K3 + 1e-3, 0.0),  # secondary peak, decaying
    (0.070, 0.080, 0.0),  # unloading from the secondary plateau (unloading ratio)
    (X1 + 0.3 * F1 / K1 + 3e-5, X1 + 0.3 * F1 / K1 + 3e-5, 1e-4),  # smoothed: in the band
    (X2 - 0.02, X2 - 0.02 + 2e-5, 1e-4),  # smoothed, unloading plateau kink band
])
def test_law_gradients_match_central_differences_at_two_steps(x, x_max, w):
    theta = jnp.zeros(len(PNAMES))
    g = np.asarray(jax.grad(_law_sum)(theta, jnp.float64(x), jnp.float64(x_max), w))
    f = jax.jit(lambda t: _law_sum(t, jnp.float64(x), jnp.float64(x_max), w))
    for h in (1e-6, 2e-6):
        fd = np.array([(float(f(theta.at[i].set(h))) - float(f(theta.at[i].set(-h)))) / (2 * h)
                       for i in range(len(PNAMES))])
        np.testing.assert_allclose(g, fd, rtol=2e-5, atol=1e-6 * np.max(np.abs(g)))


@pytest.mark.parametrize("x,x_max", [(0.0, 0.0), (X1, X1), (X1 + 0.3 * F1 / K1,) * 2,
                                     (X1 + 0.3 * F1 / K1 + 2e-3,) * 2, (X2, X2), (X4, X4),
                                     (-1e-3, 0.01)])
def test_no_nan_gradients_at_the_new_breakpoints(x, x_max):
    for w in (0.0, 1e-6):
        g = jax.grad(_law_sum, argnums=(0, 1, 2))(jnp.zeros(len(PNAMES)), jnp.float64(x),
                                                  jnp.float64(x_max), w)
        assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(g))


# --------------------------------------------------------------------------- whole landings

@pytest.fixture(scope="module")
def peak_landings():
    base = jl.simulate(t_end=0.45)
    veh = jl.vehicle_from_dict({"honeycomb": {"peak_ratio1": 1.3, "peak_length1_mm": 2.0}})
    peak = jl.simulate(vehicle=veh, t_end=0.45)
    return base, peak


def test_landing_with_a_peak_closes_its_energy_ledger_and_shows_the_peak(peak_landings):
    base, peak = peak_landings
    assert abs(peak.outcomes["energy_closure_rel"]) < 2e-4  # the default's is 6.7e-5
    primary = peak.trajectory["stroke_max_m"] < X2 - 1e-3  # before the secondary stage
    assert np.max(peak.trajectory["honeycomb_force_N"][primary]) == pytest.approx(1.3 * F1,
                                                                                rel=0.01)
    primary = base.trajectory["stroke_max_m"] < X2 - 1e-3
    assert np.max(base.trajectory["honeycomb_force_N"][primary]) == pytest.approx(F1, rel=1e-6)
    # the same landing otherwise (the peak's extra work, ~1.6 J, is small beside ~370 J crush)
    assert peak.outcomes["max_stroke_m"] == pytest.approx(base.outcomes["max_stroke_m"], rel=0.01)


def test_landing_into_the_secondary_stage_with_peaks_and_unloading_closes_its_ledger():
    veh = jl.vehicle_from_dict({"honeycomb": {"peak_ratio1": 1.2, "peak_ratio2": 1.15,
                                              "unload_ratio": 1.4}})
    r = jl.simulate(jl.Scene(drop_height=0.6), vehicle=veh, t_end=0.5)
    assert r.outcomes["max_stroke_m"] > X3 + 0.15 * F2 / K3 + 2e-3  # past the secondary peak
    assert abs(r.outcomes["energy_closure_rel"]) < 2e-4


# ------------------------------------------------------------------------------- validation

@pytest.mark.parametrize("hc,needle", [
    ({"peak_ratio1": 0.9}, "honeycomb.peak_ratio1 = 0.9: must be >= 1"),
    ({"peak_length1_mm": 0.0}, "honeycomb.peak_length1_mm = 0"),
    ({"peak_ratio1": 1.3, "peak_length1_mm": 60.0}, "must end before x_L2"),
    ({"peak_ratio2": 1.3, "peak_length2_mm": 130.0}, "must end before x_L4"),
    ({"peak_ratio1": 1.9, "peak_length1_mm": 20.0}, "must stay below F2_N"),
    ({"peak_ratio1": 1.5, "peak_length1_mm": 1.0}, "negative stiffness"),
    ({"unload_ratio": 2.0}, "unload_ratio = 2"),
])
def test_bad_peak_or_unloading_values_are_refused_by_name(hc, needle):
    with pytest.raises(jl.ConfigError) as err:
        jl.vehicle_from_dict({"honeycomb": hc})
    assert needle in str(err.value)
    assert "\n" not in str(err.value)


# ------------------------------------------------------------- tabulated strength excess

# a rise over the first fifth, then a fall with a shoulder, over 6 mm (ratios of F1)
TABLE = (0.0, 0.08, 0.15, 0.12, 0.07, 0.05, 0.03, 0.01)
TABLE_L = 6e-3


def _hc_table(table=TABLE, length=TABLE_L, r2=None, rho=None, bonded=False):
    """The paper honeycomb with the primary's tabulated excess (and the other extensions)."""
    hc = _hc(None, r2, rho, bonded=bonded)
    return eqx.tree_at(lambda h: (h.excess1, h.excess_length1), hc,
                       (jnp.asarray(table, dtype=jnp.float64), jnp.float64(length)), **_NONE)


def _expected_table_virgin(x, table=TABLE, length=TABLE_L):
    """Hand-written primary virgin curve with a table: elastic to F1 (1 + e_0), then
    F1 (1 + np.interp) over the crush past that point, 0 excess from the table's end."""
    e = np.append(table, 0.0) * F1
    nodes = np.linspace(0.0, length, len(table) + 1)
    x_on = X1 + e[0] / K1
    return np.where(x < x_on, K1 * x, F1 + np.interp(x - x_on, nodes, e))


def test_excess_table_virgin_curve_is_the_interpolated_table():
    hc = _hc_table()
    xs = np.linspace(0.0, X2 - 1e-3, 40_001)
    expected = _expected_table_virgin(xs)
    closed = jax.vmap(lambda x: laws.honeycomb_virgin_force(x, hc))(jnp.asarray(xs))
    np.testing.assert_allclose(closed, expected, rtol=1e-11, atol=1e-6)
    memory = jax.vmap(lambda x: laws.honeycomb(x, x, hc).force)(jnp.asarray(xs))
    np.testing.assert_allclose(memory, expected, rtol=1e-11, atol=1e-6)
    # an excess that starts at its top (a jump at the onset) rises elastically to it
    hc = _hc_table((0.2, 0.1, 0.05), 4e-3)
    memory = jax.vmap(lambda x: laws.honeycomb(x, x, hc).force)(jnp.asarray(xs))
    np.testing.assert_allclose(memory, _expected_table_virgin(xs, (0.2, 0.1, 0.05), 4e-3),
                               rtol=1e-11, atol=1e-6)


def test_two_node_table_is_the_linear_peak():
    """The table (a / F1) over L is the law's own linear peak r = 1 + a / F1 over L: same
    force, energies and plastic set along a load / unload / reload history."""
    xs = _path(0.0, 0.003, 0.0005, 0.009, 0.001, 0.065, 0.061, 0.0715, n=20_001)
    for w in (0.0, 1e-5):
        ref = _run(_hc(1.3, None, None, 4e-3), xs, w)
        got = _run(_hc_table((0.3,), 4e-3), xs, w)
        for a, b in zip(ref, got):
            np.testing.assert_allclose(b, a, rtol=1e-11, atol=1e-8)


@pytest.mark.parametrize("w", [0.0, 1e-6])
def test_excess_only_on_virgin_material(w):
    """Crushed past the table and reloaded: only the plateau. Unloaded inside the table:
    reloads to the strength left at the largest stroke, then follows the table on."""
    hc = _hc_table()
    x_on = X1  # e_0 = 0: the excess starts at x_L1
    x_m = x_on + TABLE_L + 3e-3
    f, *_ = _run(hc, _path(0.0, x_m, 0.0, x_m + 10e-3), w)
    tol = 2.0 * K1 * w + 1e-6
    assert np.max(f[:100_000]) >= F1 * (1 + max(TABLE)) * (1 - 1e-3)  # the virgin peak
    assert np.max(f[2 * 100_000:]) <= F1 * (1 + 1e-9) + tol
    # unloaded at the table's top and in its fall, reloaded: back to the strength left at the
    # largest stroke (the falling table is higher just below it), then on along the table
    for c_m in (2.0, 3.3):
        x_m = x_on + c_m * TABLE_L / len(TABLE)
        left = _expected_table_virgin(x_m)
        f, *_ = _run(hc, _path(0.0, x_m, x_m - 1e-3, x_m + TABLE_L), w)
        assert np.max(f[100_000:]) <= left + tol
        assert np.max(f[100_000:]) >= left - tol - 1e-6 * F1  # reached it again
        np.testing.assert_allclose(f[-1], F1, atol=tol)


TABLE_CASES = {
    "table": dict(),
    "table_jump_start": dict(table=(0.2, 0.1, 0.05, 0.02), length=5e-3),
    "table_peak2_unloading_bonded": dict(r2=1.2, rho=1.3, bonded=True),
}


@pytest.mark.parametrize("case", sorted(TABLE_CASES))
def test_work_of_the_force_with_an_excess_table_is_stored_plus_crushed(case):
    """The energy ledger with the table: integral F dx along load / unload / reload cycles
    (one inside the table) equals the change of elastic + crush energy, crush never
    decreases and the plastic set never shrinks."""
    kw = TABLE_CASES[case]
    hc = _hc_table(**kw)
    xs = _path(0.0, 0.0025, 0.0005, 0.004, 0.0, 0.009, -0.002 if kw.get("bonded") else 0.001,
               0.065, 0.061, 0.0715, 0.07, 0.12)
    f, el, cr, ps = _assert_ledger_closes(hc, xs)
    # the excess's own work, integrated independently: crush at the end of the primary stage
    # less the plateau's, against the area between the virgin curve and F1 ...
    i = np.argmax(xs >= 0.0575)  # past the table, still on the primary plateau
    x_on = X1 + kw.get("table", TABLE)[0] * F1 / K1
    c = np.linspace(0.0, kw.get("length", TABLE_L), 200_001)
    e = _expected_table_virgin(x_on + c, kw.get("table", TABLE), kw.get("length", TABLE_L)) - F1
    area = np.sum(0.5 * (e[1:] + e[:-1]) * np.diff(c))
    e0 = kw.get("table", TABLE)[0] * F1
    # ... plus the elastic energy the onset's jump e_0 releases when the force falls back
    expected = F1 * ps[i] + area + e0**2 / (2 * K1)
    np.testing.assert_allclose(cr[i], expected, rtol=1e-7)


TNAMES = ("excess1", "excess_length1", "F1", "k_b1")


def _table_sum(theta, x, x_max, w):
    hc = _hc_table(r2=1.2, rho=1.3)
    scale = jnp.exp(theta[:len(TNAMES) - 1 + len(TABLE)])
    t = hc.excess1 * scale[:len(TABLE)]
    rest = tuple(getattr(hc, n) * s for n, s in zip(TNAMES[1:], scale[len(TABLE):]))
    hc = eqx.tree_at(lambda h: (h.excess1,) + tuple(getattr(h, n) for n in TNAMES[1:]), hc,
                     (t,) + rest)
    o = laws.honeycomb(x, x_max, hc, w)
    return o.force / 1e3 + o.elastic_energy + o.crush_energy + o.plastic_set * 1e3


_DC = TABLE_L / len(TABLE)


@pytest.mark.parametrize("x,x_max,w", [
    (X1 + 0.6 * _DC, X1 + 0.6 * _DC, 0.0),  # rising, on the virgin curve
    (X1 + 3.3 * _DC - 2e-4, X1 + 3.3 * _DC, 0.0),  # unloaded inside the fall
    (X1 + 5.5 * _DC, X1 + 5.5 * _DC, 1e-4),  # smoothed
    (0.03, 0.031, 0.0),  # past the table, unloaded
])
def test_excess_table_gradients_match_central_differences(x, x_max, w):
    theta = jnp.zeros(len(TABLE) + len(TNAMES) - 1)
    g = np.asarray(jax.grad(_table_sum)(theta, jnp.float64(x), jnp.float64(x_max), w))
    f = jax.jit(lambda t: _table_sum(t, jnp.float64(x), jnp.float64(x_max), w))
    for h in (1e-6, 2e-6):
        fd = np.array([(float(f(theta.at[i].set(h))) - float(f(theta.at[i].set(-h)))) / (2 * h)
                       for i in range(theta.size)])
        np.testing.assert_allclose(g, fd, rtol=2e-5, atol=1e-6 * np.max(np.abs(g)))


@pytest.mark.parametrize("x,x_max", [(X1, X1), (X1 + 2 * _DC,) * 2, (X1 + TABLE_L,) * 2,
                                     (X1 + 2 * _DC - 1e-4, X1 + 2 * _DC), (-1e-3, 0.01)])
def test_no_nan_gradients_at_the_table_nodes(x, x_max):
    for w in (0.0, 1e-6):
        g = jax.grad(_table_sum, argnums=(0, 1, 2))(jnp.zeros(len(TABLE) + len(TNAMES) - 1),
                                                    jnp.float64(x), jnp.float64(x_max), w)
        assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(g))


def test_landing_with_an_excess_table_closes_its_ledger_and_carries_the_table():
    veh = jl.vehicle_from_dict({"honeycomb": {"excess1": list(TABLE),
                                              "excess_length1_mm": TABLE_L * 1e3}})
    r = jl.simulate(vehicle=veh, t_end=0.45)
    assert abs(r.outcomes["energy_closure_rel"]) < 2e-4
    tr = r.trajectory
    primary = tr["stroke_max_m"] < X2 - 1e-3
    assert np.max(tr["honeycomb_force_N"][primary]) == pytest.approx(F1 * (1 + max(TABLE)),
                                                                     rel=0.01)


def test_excess_table_in_toml_round_trips_and_empty_is_off(tmp_path):
    assert jl.paper_vehicle().honeycomb.excess1 is None
    assert jl.vehicle_from_dict({"honeycomb": {"excess1": []}}).honeycomb.excess1 is None
    on = jl.vehicle_from_dict({"honeycomb": {"excess1": list(TABLE), "excess_length1_mm": 6.0}})
    (tmp_path / "v.toml").write_text(jl.vehicle_to_toml(on))
    back = jl.load_vehicle(tmp_path / "v.toml")
    np.testing.assert_array_equal(np.asarray(back.honeycomb.excess1), TABLE)
    assert float(back.honeycomb.excess_length1) == 6e-3


@pytest.mark.parametrize("hc,needle", [
    ({"excess1": [-0.1, 0.0]}, "honeycomb.excess1 = -0.1: must be >= 0"),
    ({"excess1": "0.1"}, "must be a list of numbers"),
    ({"excess1": [0.1], "peak_ratio1": 1.1}, "give either peak_ratio1 or excess1"),
    ({"excess1": [0.1], "excess_length1_mm": 60.0}, "must end before x_L2"),
    ({"excess1": [0.0, 0.9]}, "must stay below F2_N"),
    ({"excess1": [0.0, 0.5], "excess_length1_mm": 0.4}, "must be < k_b1"),
    ({"excess1": [0.3], "excess_length1_mm": 1.0}, "negative stiffness"),
])
def test_bad_excess_tables_are_refused_by_name(hc, needle):
    with pytest.raises(jl.ConfigError) as err:
        jl.vehicle_from_dict({"honeycomb": hc})
    assert needle in str(err.value)
    assert "\n" not in str(err.value)


# ------------------------------------------------------------------ a peak that builds up

RISE = dict(r1=1.25, L1=3e-3, rise=1.5e-3)


def _hc_rise(r1=RISE["r1"], L1=RISE["L1"], rise=RISE["rise"], r2=None, rho=None):
    hc = _hc(r1, r2, rho, L1)
    return eqx.tree_at(lambda h: h.peak_rise1, hc, jnp.float64(rise), **_NONE)


def test_peak_with_a_rise_length_builds_up_then_falls():
    """Elastic to F1 at x_L1, a linear rise to r1 F1 over the rise length, a linear fall to F1
    over peak_length1 (hand-written with np.interp); reloading after the peak: the plateau."""
    r1, L1, rise = RISE["r1"], RISE["L1"], RISE["rise"]
    hc = _hc_rise()
    xs = np.linspace(0.0, X2 - 1e-3, 40_001)
    expected = np.where(xs < X1, K1 * xs, np.interp(xs - X1, [0.0, rise, rise + L1],
                                                    [F1, r1 * F1, F1]))
    for f in (lambda x: laws.honeycomb(x, x, hc).force,
              lambda x: laws.honeycomb_virgin_force(x, hc)):
        np.testing.assert_allclose(jax.vmap(f)(jnp.asarray(xs)), expected, rtol=1e-11,
                                   atol=1e-6)
    f, *_ = _run(hc, _path(0.0, X1 + rise + L1 + 1e-3, 0.0, X1 + rise + L1 + 5e-3))
    assert np.max(f[2 * 100_000:]) <= F1 * (1 + 1e-9)


def test_work_of_the_force_with_a_rising_peak_is_stored_plus_crushed():
    """The ledger of the hard law (the smoothed law keeps the hard law's closed forms, off by
    as much as the paper law's own smoothing) along a history unloaded in the build-up."""
    w = 0.0
    hc = _hc_rise(r2=1.2, rho=1.3)
    x_mid = X1 + 0.5 * RISE["rise"]  # unloaded while the peak is still building up
    xs = _path(0.0, x_mid, x_mid - 5e-4, 0.004, 0.001, 0.065, 0.061, 0.0715, 0.07, 0.12)
    f, el, cr, ps = _run(hc, xs, w)
    work = np.cumsum(np.concatenate([[0.0], 0.5 * (f[1:] + f[:-1]) * np.diff(xs)]))
    scale = el[-1] + cr[-1]
    np.testing.assert_allclose(work, el + cr, rtol=0, atol=2e-9 * scale)
    assert np.all(np.diff(cr) >= -1e-9 * scale)
    assert np.all(np.diff(ps) >= -1e-15)
    # reloaded in the build-up: back to the strength reached, then on up the rise
    i = 2 * 100_000
    s_mid = F1 * (1 + (RISE["r1"] - 1) * 0.5)
    assert np.max(f[100_000:i]) <= s_mid + 2 * K1 * w + 1e-6


RNAMES = ("peak_ratio1", "peak_length1", "peak_rise1", "F1", "k_b1")


def _rise_sum(theta, x, x_max, w):
    hc = _hc_rise()
    vals = tuple(getattr(hc, n) * jnp.exp(t) for n, t in zip(RNAMES, theta))
    hc = eqx.tree_at(lambda h: tuple(getattr(h, n) for n in RNAMES), hc, vals)
    o = laws.honeycomb(x, x_max, hc, w)
    return o.force / 1e3 + o.elastic_energy + o.crush_energy + o.plastic_set * 1e3


@pytest.mark.parametrize("x,x_max,w", [
    (X1 + 0.7e-3, X1 + 0.7e-3, 0.0),  # building up, virgin
    (X1 + 2.5e-3, X1 + 2.6e-3, 0.0),  # unloaded in the fall
    (X1 + 1.5e-3, X1 + 1.5e-3 + 2e-5, 1e-4),  # smoothed, at the top
])
def test_rising_peak_gradients_match_central_differences(x, x_max, w):
    theta = jnp.zeros(len(RNAMES))
    g = np.asarray(jax.grad(_rise_sum)(theta, jnp.float64(x), jnp.float64(x_max), w))
    assert np.all(np.isfinite(g))
    f = jax.jit(lambda t: _rise_sum(t, jnp.float64(x), jnp.float64(x_max), w))
    for h in (1e-6, 2e-6):
        fd = np.array([(float(f(theta.at[i].set(h))) - float(f(theta.at[i].set(-h)))) / (2 * h)
                       for i in range(theta.size)])
        np.testing.assert_allclose(g, fd, rtol=2e-5, atol=1e-6 * np.max(np.abs(g)))


def test_rise_length_in_toml_off_by_zero_and_refused_by_name(tmp_path):
    assert jl.paper_vehicle().honeycomb.peak_rise1 is None
    assert jl.vehicle_from_dict({"honeycomb": {"peak_rise1_mm": 0.0}}).honeycomb.peak_rise1 \
        is None
    on = jl.vehicle_from_dict({"honeycomb": {"peak_ratio1": 1.2, "peak_rise1_mm": 1.5}})
    (tmp_path / "v.toml").write_text(jl.vehicle_to_toml(on))
    assert float(jl.load_vehicle(tmp_path / "v.toml").honeycomb.peak_rise1) == 1.5e-3
    for hc, needle in (({"peak_ratio1": 1.2, "peak_rise1_mm": 0.05}, "must be < k_b1"),
                       ({"peak_ratio1": 1.2, "peak_rise1_mm": 56.0}, "must end before x_L2"),
                       ({"excess1": [0.1], "peak_rise1_mm": 0.002},
                        "peak_rise1_mm = 0.002: the excess builds up"),
                       ({"excess1": [0.1], "excess_length1_mm": 10.0, "peak_rise1_mm": 48.0},
                        "excess must end before x_L2")):
        with pytest.raises(jl.ConfigError, match=needle):
            jl.vehicle_from_dict({"honeycomb": hc})


# a table after a build-up (calibration's rise_exp form): 0 -> e_0 over the rise, then the
# table; ratios of F1
RISE_TABLE = (0.2, 0.12, 0.07, 0.04, 0.02)
RISE_TABLE_L, RISE_TABLE_RISE = 5e-3, 1.2e-3


def _hc_rise_table(r2=None, rho=None):
    hc = _hc_table(RISE_TABLE, RISE_TABLE_L, r2, rho)
    return eqx.tree_at(lambda h: h.peak_rise1, hc, jnp.float64(RISE_TABLE_RISE), **_NONE)


def _expected_rise_table_virgin(x):
    """Hand-written: elastic to F1 at x_L1, linear to F1 (1 + e_0) over the rise, then the
    table interpolated over its length, 0 excess from its end."""
    e = np.append(RISE_TABLE, 0.0) * F1
    c = np.concatenate([[0.0], RISE_TABLE_RISE + np.linspace(0.0, RISE_TABLE_L, len(e))])
    return np.where(x < X1, K1 * x, F1 + np.interp(x - X1, c, np.concatenate([[0.0], e])))


def test_a_table_after_a_rise_builds_up_then_follows_the_table(tmp_path):
    hc = _hc_rise_table()
    xs = np.linspace(0.0, X2 - 1e-3, 40_001)
    expected = _expected_rise_table_virgin(xs)
    for f in (lambda x: laws.honeycomb(x, x, hc).force,
              lambda x: laws.honeycomb_virgin_force(x, hc)):
        np.testing.assert_allclose(jax.vmap(f)(jnp.asarray(xs)), expected, rtol=1e-11,
                                   atol=1e-6)
    # the ledger along load / unload / reload, once unloaded in the build-up and once in the
    # table; the excess's work, integrated independently, is the crush beyond the plateau's
    x_mid = X1 + 0.5 * RISE_TABLE_RISE
    x_tab = X1 + RISE_TABLE_RISE + 0.3 * RISE_TABLE_L
    hs = _path(0.0, x_mid, x_mid - 5e-4, x_tab, x_tab - 1e-3, 0.009, 0.001, 0.065, 0.061,
               0.0715, 0.07, 0.12)
    f, el, cr, ps = _assert_ledger_closes(_hc_rise_table(r2=1.2, rho=1.3), hs)
    i = np.argmax(hs >= 0.0575)
    c = np.linspace(0.0, RISE_TABLE_RISE + RISE_TABLE_L, 200_001)
    e = _expected_rise_table_virgin(X1 + c) - F1
    area = np.sum(0.5 * (e[1:] + e[:-1]) * np.diff(c))
    np.testing.assert_allclose(cr[i], F1 * ps[i] + area, rtol=1e-7)
    # reloaded after the excess: the plateau only; the TOML carries both
    f, *_ = _run(hc, _path(0.0, X1 + RISE_TABLE_RISE + RISE_TABLE_L + 1e-3, 0.0,
                           X1 + RISE_TABLE_RISE + RISE_TABLE_L + 5e-3))
    assert np.max(f[2 * 100_000:]) <= F1 * (1 + 1e-9)
    veh = eqx.tree_at(lambda v: v.honeycomb, jl.paper_vehicle(), hc)
    (tmp_path / "v.toml").write_text(jl.vehicle_to_toml(jl.validate_vehicle(veh)))
    back = jl.load_vehicle(tmp_path / "v.toml").honeycomb
    assert float(back.peak_rise1) == RISE_TABLE_RISE
    np.testing.assert_array_equal(np.asarray(back.excess1), RISE_TABLE)


def _with_node_values(cv):
    """The curve ``cv`` with the optional node values and integrals of its table, computed
    here by numpy from the segments (``HoneycombCurve.t1_e``, ``t1_int``)."""
    c0, dc, s = (np.broadcast_to(np.asarray(t, float), cv.t1_c.shape)
                 for t in (cv.t1_c, cv.t1_dc, cv.t1_slope))
    e = float(cv.a1) + np.concatenate([[0.0], np.cumsum(s * dc)[:-1]])
    area = np.concatenate([[0.0], np.cumsum(e * dc + 0.5 * s * dc * dc)[:-1]])
    return eqx.tree_at(lambda c: (c.t1_e, c.t1_int), cv, (jnp.asarray(e), jnp.asarray(area)),
                       **_NONE)


@pytest.mark.parametrize("table", ["uniform", "rise", "zero-width segments"])
def test_a_table_read_at_its_segment_is_the_summed_table(table):
    """With the node values and integrals the law reads the one segment that holds the crush:
    force, energies and plastic set as the sum over every segment, along load / unload /
    reload through every node, zero-width segments (equal starts) included."""
    if table == "uniform":
        cv = _hc_table(r2=1.2, rho=1.3).curve()
    elif table == "rise":
        cv = eqx.tree_at(lambda h: h.peak_rise1, _hc(1.25, None, None, 1.5e-3), 1e-3,
                         **_NONE).curve()
    else:  # one falling segment, then segments of width 0 at its end (calibration's forms)
        cv = _hc(1.3, None, None, 4e-3).curve()
        z = jnp.zeros(4)
        cv = eqx.tree_at(
            lambda c: (c.t1_c, c.t1_dc, c.t1_slope), cv,
            (jnp.concatenate([jnp.zeros(1), jnp.full(4, cv.L1)]),
             jnp.concatenate([cv.L1[None], z]), jnp.concatenate([(-cv.a1 / cv.L1)[None], z])),
            **_NONE)
    read = _with_node_values(cv)
    assert cv.t1_e is None and read.t1_e is not None
    xs = _path(0.0, 0.004, 0.0012, 0.0065, 0.0015, 0.065, 0.061, 0.0715)
    for a, b in zip(_run(cv, xs), _run(read, xs)):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-9)
    _assert_ledger_closes(read, xs)
