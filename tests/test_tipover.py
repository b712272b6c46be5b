"""Stability margin and tip-over of the full 3-D model, against geometry and the README's claims.

References, independent of the code under test:
- the paper vehicle's footprint from its Table 2 geometry (config fields R, L_h0, theta_b):
  foot radius r_f = R + L_h0 cos(theta_b) = 0.6 + 3.19 cos(58.7 deg) = 2.2573 m (README
  "Quarter model": the foot rests at (2.257, -2.976) m); with four legs at 0, 90, 180, 270 deg
  the centre of mass at rest is d = r_f cos(45 deg) = 1.5961 m from each edge of the square;
- the documented soft minimum over edges, m = -tau log sum_i exp(-d_i / tau), tau = 1 cm
  (README "Full 3-D model": "width 1 cm, which reads about 1.4 cm low at rest": tau log 4);
- the README's tip-over bracket: friction 2, sink 1 m/s, heading 45 deg, drop height 0, "it tips
  between 3.0 and 3.25 m/s".
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxland as jl

VEH = jl.paper_vehicle()
TAU = 0.01  # m, the README's soft-min width
REST = jl.Solver(dt=1e-5, t_end=2e-3, save_dt=1e-3)  # two steps' worth: the state at release


def _foot_radius() -> float:
    leg = VEH.leg
    return float(leg.R) + float(leg.L_h0) * math.cos(float(leg.theta_b))


def _soft_min(d) -> float:
    d = np.asarray(d, dtype=float)
    return float(-TAU * np.log(np.sum(np.exp(-d / TAU))))


@pytest.fixture(scope="module")
def margin_at_release():
    fn = jax.jit(lambda s: jl.landing(VEH, s, REST, "full")[0]["stability_margin_m"][0])
    return lambda scene: float(fn(scene))


def test_footprint_is_the_paper_geometry():
    """Table 2 geometry (not the code) gives the foot radius the README states."""
    assert _foot_radius() == pytest.approx(0.6 + 3.19 * math.cos(math.radians(58.7)), abs=1e-9)
    assert _foot_radius() == pytest.approx(2.257, abs=5e-4)


def test_margin_at_rest_is_the_edge_distance_less_the_soft_min_offset(margin_at_release):
    """Level vehicle released above level ground: every edge is d = r_f / sqrt(2) = 1.5961 m
    from the CoM, and the soft minimum of four equal distances is d - tau log 4 = 1.5823 m.
    A 10x soft-min width reads d - 0.139 m; a hard minimum reads d: both fail at 1e-6 m."""
    d = _foot_radius() / math.sqrt(2.0)
    got = margin_at_release(jl.Scene(drop_height=0.1))
    assert got == pytest.approx(d - TAU * math.log(4.0), abs=1e-6)
    assert d - got == pytest.approx(0.0139, abs=1e-4)  # "about 1.4 cm low at rest"


def test_margin_with_an_offset_centre_of_mass(margin_at_release):
    """CoM 0.1 m forward (+x, towards leg 0): the two front edges (normals at +/-45 deg) come
    0.1 / sqrt(2) closer and the two rear ones move as far away; the soft minimum of the four,
    computed here from the definition, is 1.5185 m."""
    d = _foot_radius() / math.sqrt(2.0)
    off = 0.1 / math.sqrt(2.0)
    got = margin_at_release(jl.Scene(drop_height=0.1, com_offset=(0.1, 0.0, 0.0)))
    assert got == pytest.approx(_soft_min([d - off, d - off, d + off, d + off]), abs=1e-6)


def test_margin_on_a_slope_is_measured_in_the_ground_plane(margin_at_release):
    """Level vehicle above ground sloping by s = 0.1 rad downhill along +x: CoM and feet are
    projected along gravity onto the plane, where distances along x stretch by 1 / cos s. The
    feet sit at (r_f / cos s, 0), (0, r_f), ... in the plane's coordinates, so each edge is
    r_f / sqrt(1 + cos^2 s) from the CoM (1.6001 m against 1.5961 m on level ground).
    Projecting along the ground normal instead would give the level value."""
    s = 0.1
    d = _foot_radius() / math.sqrt(1.0 + math.cos(s) ** 2)
    got = margin_at_release(jl.Scene(drop_height=0.1, slope=s, slope_direction=0.0))
    assert got == pytest.approx(d - TAU * math.log(4.0), abs=1e-6)


BRACKET = (3.0, 3.25)  # m/s, README "Tip-over boundary": "it tips between 3.0 and 3.25 m/s"


@pytest.fixture(scope="module")
def bracket_outcomes():
    """The README's scene at both ends of its bracket, one vmapped batch. 1.4 s covers the
    upright case's deepest margin (measured at 1.18 s) and the tip (at 0.69 s)."""
    solver = jl.Solver(dt=1e-5, t_end=1.4, save_dt=0.1)
    scenes = jl.Scene.batch(horizontal_speed=jnp.array(BRACKET), drop_height=0.0,
                            sink_speed=1.0, heading=math.pi / 4, friction=2.0)
    out = jax.jit(lambda s: jl.landings(VEH, s, solver, "full")[1])(scenes)
    return {k: np.asarray(v) for k, v in out.items()}


def test_tip_over_bracket_as_the_readme_states_it(bracket_outcomes):
    """3.0 m/s towards the edge between two feet stays upright, 3.25 m/s tips. The bracket is
    narrow (8 %): a 4x body inertia moves the rigid-body boundary by sqrt(I_edge) = +11 %
    (3.3 -> 3.7 m/s), enough that 3.25 m/s no longer tips."""
    out = bracket_outcomes
    margin = -out["peak_margin_deficit_m"]
    assert not bool(out["tipped"][0]) and margin[0] > 0.0, margin  # 3.0: upright
    assert bool(out["tipped"][1]) and margin[1] < 0.0, margin  # 3.25: tips
    # the upright one came close: it leaned well past half the tipping angle atan(d/h)
    d = _foot_radius() / math.sqrt(2.0)
    h = float(VEH.leg.H1) + float(VEH.leg.L_h0) * math.sin(float(VEH.leg.theta_b))
    assert out["peak_tilt_deg"][0] > 0.5 * math.degrees(math.atan2(d, h))
