"""Parameters of the vehicle, as pytrees (``eqx.Module``), separate from any state.

Every field carries its SI unit, its source (paper table/equation, or our assumption with the
reasoning) and the rule a valid value obeys, in ``metadata``. The TOML format, ``jaxland
config`` and the validation messages are all generated from that metadata, so the docs and the
checks cannot drift apart.

Symbols follow the paper (Table 2, section 2.3): k, gamma, chi, mu, k_tan, D_b, k_b1, k_b3,
x_L1..x_L4. Lengths are metres, forces newtons, angles radians inside the code (degrees in TOML).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Honeycomb", "Leg", "Ground", "Vehicle", "field_info"]


def _kind(x) -> str | None:
    """The numpy dtype kind of a value (None for a traced one: its dtype is the program's)."""
    if isinstance(x, jax.core.Tracer):
        return None
    dtype = getattr(x, "dtype", None)
    if dtype is None:
        try:
            dtype = np.asarray(x).dtype
        except (TypeError, ValueError):  # a ragged list
            return "O"
    return np.dtype(dtype).kind


def _f64(x, name: str = "value"):
    # a flag or a text would convert (True to 1.0, "0.2" to 0.2): refused as the typo it is
    if _kind(x) not in ("b", "U", "S", "O"):
        try:
            return jnp.asarray(x, dtype=jnp.float64)
        except (TypeError, ValueError):
            pass
    from ._errors import ConfigError

    raise ConfigError(name, x, "must be a number or an array of numbers") from None


def _opt_f64(x, name: str = "value"):
    return None if x is None else _f64(x, name)


def _opt_table(x):
    """A strength-excess table as a float64 array, or None (off) for None or an empty table."""
    if x is None:
        return None
    x = jnp.asarray(x, dtype=jnp.float64)
    return None if x.size == 0 else x


def concrete(x):
    """``x`` as a float numpy array, or None if it is None or a tracer (inside jit/vmap/grad,
    where values cannot be checked)."""
    if x is None:
        return None
    try:
        return np.asarray(x, dtype=float)
    except Exception:
        return None


def _param(unit: str, doc: str, source: str, rule: str, *, toml: str, to_si: float = 1.0,
           off: float | None = None, **default):
    """A float64 parameter field with its unit, source, validity rule and TOML key.

    The optional extensions of the paper's laws have ``off`` (the value that means "not used",
    documented and written to TOML) and default None: a None field is structurally absent (the
    law takes the paper's code path, bit for bit, under jit too) and ``_config`` maps the ``off``
    value in a TOML file to None. ``default=`` gives a plain default."""
    if off is not None:
        return eqx.field(
            converter=_opt_f64, default=None,
            metadata=dict(unit=unit, doc=doc, source=source, rule=rule, toml=toml, to_si=to_si,
                          off=off),
        )
    return eqx.field(
        converter=_f64,
        metadata=dict(unit=unit, doc=doc, source=source, rule=rule, toml=toml, to_si=to_si),
        **default,
    )


def field_info(module_cls) -> list[dataclasses.Field]:
    """The documented parameter fields of a parameter Module class (in declaration order)."""
    return [f for f in dataclasses.fields(module_cls) if "unit" in f.metadata]


class Honeycomb(eqx.Module):
    """Two-stage aluminium-honeycomb buffer in the main strut (paper section 2.3, Fig. 5).

    Virgin curve: elastic ``k_b1`` up to ``x_L1 = F1 / k_b1``, ideal plateau ``F1`` (the paper's
    k_b2 = 0) to ``x_L2``, elastic ``k_b3`` to ``x_L3 = x_L2 + (F2 - F1) / k_b3``, ideal plateau
    ``F2`` (k_b4 = 0) to ``x_L4``, then bottoming out on ``k_bottom``. Unloading and reloading
    follow the stack's elastic law from the plastic set reached (see ``jaxland._laws._honeycomb``).

    Three optional extensions, off by default (the paper's law, bit for bit): an initial crush
    peak per stage on virgin material (``peak_ratio1/2``, ``peak_length1/2``), a tabulated
    strength excess of the primary stage on virgin material (``excess1``, ``excess_length1``:
    any peak shape, e.g. a measured one) and the unloading stiffness of the secondary stage
    (``unload_ratio``).
    """

    k_b1: jnp.ndarray = _param(
        "N/m", "elastic stiffness of the primary honeycomb stage",
        "our assumption: F1 / x_L1 with the paper's x_L1 = 0.47 mm (Table 2)", "> 0",
        toml="k_b1_N_per_m")
    F1: jnp.ndarray = _param(
        "N", "plateau (mean crush) force of the primary honeycomb",
        "our calibration: Wierzbicki (1983) crush stress 6.6 sigma_0 (t/D)^(5/3) on Table 1's "
        "98 mm section, with sigma_0 chosen to reproduce the paper's 66.5 mm first-impact stroke",
        "> 0", toml="F1_N")
    x_L2: jnp.ndarray = _param(
        "m", "stroke at the end of the primary plateau (primary honeycomb fully crushed)",
        "paper Table 2 (57.60 mm)", "> x_L1", toml="x_L2_mm", to_si=1e-3)
    k_b3: jnp.ndarray = _param(
        "N/m", "elastic stiffness of the secondary honeycomb stage",
        "our assumption: (F2 - F1) / (x_L3 - x_L2) with the paper's x_L3 - x_L2 = 0.63 mm",
        "> 0", toml="k_b3_N_per_m")
    F2: jnp.ndarray = _param(
        "N", "plateau (mean crush) force of the secondary honeycomb",
        "our calibration: Wierzbicki (1983) with Table 1's cell size and foil, same sigma_0 as F1",
        "> F1", toml="F2_N")
    x_L4: jnp.ndarray = _param(
        "m", "stroke at the end of the secondary plateau (both stages crushed; bottoming out)",
        "paper Table 2 (183.23 mm)", "> x_L3", toml="x_L4_mm", to_si=1e-3)
    k_bottom: jnp.ndarray = _param(
        "N/m", "stiffness of the fully crushed stack (bottoming out) beyond x_L4",
        "our assumption: a stiff stop, 1e8 N/m; reaching it is reported as bottoming out", "> 0",
        toml="k_bottom_N_per_m")
    peak_ratio1: jnp.ndarray = _param(
        "1", "initial crush peak of the virgin primary honeycomb over its plateau, r1 = peak / F1 "
        "(1: no peak). The elastic rise continues to r1 F1, then the force falls linearly to F1 "
        "over peak_length1_mm of crush; an already crushed block has no peak",
        "literature: bare (not pre-crushed) aluminium honeycomb peaks at about 1.5-2 x its crush "
        "plateau (Hexcel HexWeb data: bare compressive strength vs crush strength; Wu & Jiang, "
        "Int. J. Impact Eng. 19 (1997) 439-456); pre-crushed honeycomb about 1.0-1.3 x (the "
        "pre-crush removes most but not all of it, as the paper notes for its own drop test). "
        "Default 1, the paper's simulation",
        ">= 1", toml="peak_ratio1", off=1.0)
    peak_length1: jnp.ndarray = _param(
        "m", "crush over which the primary peak falls back to F1 (linear decay)",
        "our assumption: 2 mm, between the half fold H = 0.821 t^(1/3) D^(2/3) ~ 1.4 mm and the "
        "fold 2H ~ 2.9 mm of Table 1's primary cells (Wierzbicki 1983); fit it from a drop "
        "record. Unused while peak_ratio1 = 1",
        "> 0", toml="peak_length1_mm", to_si=1e-3, default=2e-3)
    peak_rise1: jnp.ndarray = _param(
        "m", "crush over which the primary peak builds up: with it, the elastic rise ends at F1 "
        "and the strength rises linearly from F1 to peak_ratio1 F1 over this much crush, then "
        "falls over peak_length1_mm; with excess1 instead, it rises linearly from F1 to "
        "F1 (1 + e_0) and then follows the table (0: off, the elastic rise goes to the peak "
        "itself)",
        "our extension (issue 12): a peak that builds up while the first folds form; fit it "
        "from a drop record. Default off. Unused while peak_ratio1 = 1 and excess1 is off",
        "> 0", toml="peak_rise1_mm", to_si=1e-3, off=0.0)
    peak_ratio2: jnp.ndarray = _param(
        "1", "initial crush peak of the virgin secondary honeycomb over its plateau, r2 = peak / "
        "F2 (1: no peak); as peak_ratio1, from x_L3 on",
        "literature range as peak_ratio1 (bare ~1.5-2, pre-crushed ~1.0-1.3). Default 1",
        ">= 1", toml="peak_ratio2", off=1.0)
    peak_length2: jnp.ndarray = _param(
        "m", "crush over which the secondary peak falls back to F2 (linear decay)",
        "our assumption: 2 mm, as peak_length1. Unused while peak_ratio2 = 1",
        "> 0", toml="peak_length2_mm", to_si=1e-3, default=2e-3)
    excess1: jnp.ndarray = eqx.field(
        converter=_opt_table, default=None,
        metadata=dict(
            unit="1", toml="excess1", to_si=1.0, off=(), table=True,
            doc="tabulated strength excess of the virgin primary honeycomb over its plateau, as "
                "ratios of F1: the values e_j / F1 at the crush c_j = j excess_length1_mm / n "
                "(j = 0 .. n-1, n the table's length), piecewise linear between them and 0 from "
                "c = excess_length1_mm on. c is the crush past the onset x_L1 + e_0 / k_b1 "
                "(where the elastic rise meets F1 + e_0), or, with peak_rise1_mm, past the end "
                "of that linear build-up from F1 (which starts at x_L1); the strength is "
                "F1 + e(c) as a function "
                "of the largest stroke reached, so an already crushed block has no excess. Any "
                "peak shape (a rise, a fall, fold ripples); [] or absent: off. Not with "
                "peak_ratio1",
            source="our extension (issue 12): a measured or modelled peak shape; the virtual "
                   "rig's physical crush peaks use it. Default off",
            rule=">= 0"))
    excess_length1: jnp.ndarray = _param(
        "m", "crush length the excess1 table spans (the excess is 0 from there on)",
        "our assumption: 10 mm. Unused while excess1 is off",
        "> 0", toml="excess_length1_mm", to_si=1e-3, default=1e-2)
    unload_ratio: jnp.ndarray = _param(
        "1", "unloading stiffness of the secondary stage over its loading stiffness, "
        "k_u = unload_ratio k_b3. 1: a crushed stack unloads back along k_b3 to F1, then along "
        "k_b1 (both blocks in series). Above 1 part of the k_b3 rise is plastic set and the stack "
        "unloads stiffer; unload_ratio = k_b1 / k_b3 unloads the whole stack along the single "
        "stiffness k_b1. It sets the final stroke of drops reaching the secondary stage",
        "our assumption: the paper leaves the unloading law open; default 1",
        ">= 1", toml="unload_ratio", off=1.0)
    bonded: bool = eqx.field(
        static=True, default=False,
        metadata=dict(doc="True: the crushed honeycomb is bonded to rod and sleeve and pulls "
                      "elastically below its plastic set (the paper's simulation). False "
                      "(default): it never pulls; the rod slides free down to the top-out stop "
                      "(the paper's experiment, section 3.2)", toml="bonded"))

    @property
    def x_L1(self):
        """Stroke at the end of the primary elastic stage, F1 / k_b1 [m]."""
        return self.F1 / self.k_b1

    def curve(self) -> HoneycombCurve:
        """The force law's numbers with the derived breakpoints evaluated once (do this outside
        a time loop: XLA does not hoist the divisions out of it)."""
        x_L1, x_L3 = self.x_L1, self.x_L3
        table = self.excess1 is not None
        peak = self.peak_ratio1 is not None or self.peak_ratio2 is not None or table
        unload = self.unload_ratio is not None
        ext = {}
        if peak or unload:  # the general law (every extension's term present)
            r1, r2, rho = (1.0 if r is None else r for r in (self.peak_ratio1, self.peak_ratio2,
                                                             self.unload_ratio))
            a1, a2 = (r1 - 1.0) * self.F1, (r2 - 1.0) * self.F2
            L1 = self.peak_length1
            seg = None  # the primary's excess as a table: (starts, widths, slopes) past onset
            if self.peak_rise1 is not None and self.peak_ratio1 is not None:
                # the law's linear fall as a one-segment table, a1 -> 0 over peak_length1
                # (validate_vehicle: not with excess1), to be built up over the rise below
                fall = jnp.expand_dims(L1, -1)
                seg = (jnp.zeros_like(fall), fall, -jnp.expand_dims(a1, -1) / fall)
            if table:  # the primary's excess from its table (validate_vehicle: not with r1)
                e = self.excess1 * jnp.expand_dims(self.F1, -1)  # N, at the nodes c_j
                n = e.shape[-1]
                L1 = self.excess_length1
                dc = jnp.expand_dims(L1 / n, -1)  # m, the grid step
                e_next = jnp.concatenate([e[..., 1:], jnp.zeros_like(e[..., :1])], axis=-1)
                a1 = e[..., 0]
                seg = (dc * jnp.arange(n, dtype=jnp.float64), dc, (e_next - e) / dc)
            if seg is not None and self.peak_rise1 is not None:
                # built up first: one segment 0 -> a1 over the rise, then the table
                rise = jnp.expand_dims(self.peak_rise1, -1)
                c, dc, slope = seg
                seg = (_cat(jnp.zeros_like(rise), rise + c),
                       _cat(rise, jnp.broadcast_to(dc, slope.shape)),
                       _cat(jnp.expand_dims(a1, -1) / rise, slope))
                a1, L1 = jnp.zeros_like(a1), self.peak_rise1 + L1
            if seg is not None:
                ext = dict(t1_c=seg[0], t1_dc=seg[1], t1_slope=seg[2])
            ext.update(a1=a1, x_pk1=x_L1 + a1 / self.k_b1, L1=L1,
                       a2=a2, x_pk2=x_L3 + a2 / self.k_b3, L2=self.peak_length2,
                       k_u=self.k_b3 * rho, q=1.0 - 1.0 / rho)
        return HoneycombCurve(k_b1=self.k_b1, k_b3=self.k_b3, k_bottom=self.k_bottom,
                              F1=self.F1, F2=self.F2, x_L1=x_L1, x_L2=self.x_L2,
                              x_L3=x_L3, x_L4=self.x_L4, bonded=self.bonded,
                              extended=peak or unload, **ext)

    @property
    def x_L3(self):
        """Stroke at the end of the secondary elastic stage, x_L2 + (F2 - F1) / k_b3 [m]."""
        return self.x_L2 + (self.F2 - self.F1) / self.k_b3


def _cat(*parts):
    """The segments ``parts`` (last axis) joined, their leading (per-leg, batch) axes
    broadcast to one shape first: a rise given per leg joins a table given once."""
    lead = jnp.broadcast_shapes(*(jnp.shape(p)[:-1] for p in parts))
    return jnp.concatenate([jnp.broadcast_to(p, lead + jnp.shape(p)[-1:]) for p in parts],
                           axis=-1)


class HoneycombCurve(eqx.Module):
    """``Honeycomb`` with its breakpoints evaluated: what the force law reads at every step."""

    k_b1: jnp.ndarray
    k_b3: jnp.ndarray
    k_bottom: jnp.ndarray
    F1: jnp.ndarray
    F2: jnp.ndarray
    x_L1: jnp.ndarray
    x_L2: jnp.ndarray
    x_L3: jnp.ndarray
    x_L4: jnp.ndarray
    # the extensions (None unless a peak or the unloading ratio is on: ``extended``)
    a1: jnp.ndarray | None = None  # N, primary peak over F1, (r1 - 1) F1
    x_pk1: jnp.ndarray | None = None  # m, stroke of the primary peak, x_L1 + a1 / k_b1
    L1: jnp.ndarray | None = None  # m, crush over which the primary peak decays
    a2: jnp.ndarray | None = None  # N, secondary peak over F2, (r2 - 1) F2
    x_pk2: jnp.ndarray | None = None  # m, stroke of the secondary peak, x_L3 + a2 / k_b3
    L2: jnp.ndarray | None = None  # m, crush over which the secondary peak decays
    k_u: jnp.ndarray | None = None  # N/m, secondary stage's unloading stiffness, rho k_b3
    q: jnp.ndarray | None = None  # 1, plastic fraction of the k_b3 rise, 1 - 1 / rho
    # the primary's tabulated excess (None unless ``Honeycomb.excess1`` or ``peak_rise1`` is
    # on): segments from c_j of width dc_j, e(c) = a1 + sum_j slope_j clip(c - c_j, 0, dc_j)
    t1_c: jnp.ndarray | None = None  # m, the segments' starts c_j (last axis: j = 0 .. n-1)
    t1_dc: jnp.ndarray | None = None  # m, their widths (a uniform grid: last axis of length 1)
    t1_slope: jnp.ndarray | None = None  # N/m, the excess's slope on [c_j, c_j + dc]
    # optional, with the table: the excess at each segment's start e(c_j) [N] and its integral
    # over [0, c_j] [J]; with them the unsmoothed law reads the one segment that holds c (a
    # gather) instead of summing over all of them (calibration's peak forms: 97 segments)
    t1_e: jnp.ndarray | None = None
    t1_int: jnp.ndarray | None = None
    bonded: bool = eqx.field(static=True, default=False)
    extended: bool = eqx.field(static=True, default=False)


class Leg(eqx.Module):
    """Inverted-triangle leg geometry and strut properties (paper Table 2, Figs 1 and 7).

    In the leg's vertical plane (r radial outward, z up, origin at the body centre of mass): main
    strut joint ``P = (R, -H1)``, auxiliary strut joint ``A = (R, -H1 - H2)``, the main strut of
    rest length ``L_h0`` points outward and down at ``theta_b`` below the horizontal, and the foot
    sits at its end. The auxiliary strut's rest length is derived, |F0 - A|, so the leg is
    unstressed at rest (the paper's rounded 2.04 m would pre-load it).
    """

    R: jnp.ndarray = _param("m", "radial offset of both strut joints from the body axis",
                            "paper Table 2", "> 0", toml="R_m")
    H1: jnp.ndarray = _param("m", "depth of the main-strut joint P below the body centre of mass",
                             "paper Table 2", ">= 0", toml="H1_m")
    H2: jnp.ndarray = _param("m", "depth of the auxiliary-strut joint A below P",
                             "paper Table 2", "> 0", toml="H2_m")
    L_h0: jnp.ndarray = _param("m", "rest length of the main strut, joint P to foot",
                               "paper Table 2", "> 0", toml="L_h0_m")
    theta_b: jnp.ndarray = _param(
        "rad", "main strut angle below the horizontal", "paper Table 2 (58.70 deg)",
        "in (0, 90) deg", toml="theta_b_deg", to_si=math.pi / 180.0)
    h: jnp.ndarray = _param(
        "m", "lateral half-spacing of the two auxiliary struts (used by 3-D models only)",
        "paper Table 2, our reading (docs/model.md section 2)", ">= 0", toml="h_m")
    k_a: jnp.ndarray = _param(
        "N/m", "combined axial stiffness of the leg's pair of auxiliary struts (k_a / 2 each; "
        "massless springs)",
        "our assumption: 5e6 N/m, steel tubes of a few cm^2 over 2 m; the paper gives none",
        "> 0", toml="k_a_N_per_m")
    k_topout: jnp.ndarray = _param(
        "N/m", "stiffness of the main strut's top-out stop (no extension beyond L_h0)",
        "our assumption: 1e7 N/m, a stiff mechanical stop", "> 0", toml="k_topout_N_per_m")
    D_b: jnp.ndarray = _param(
        "s/m", "structural damping of the main strut, F_bd = D_b v_b F_bh",
        "paper Table 2 and section 3.1", ">= 0", toml="D_b_s_per_m")

    @property
    def joint_P(self):
        """Main-strut joint (r, z) in the leg plane relative to the body CoM [m]."""
        return jnp.stack([self.R, -self.H1])

    @property
    def joint_A(self):
        """Auxiliary-strut joint (r, z) relative to the body CoM [m]."""
        return jnp.stack([self.R, -self.H1 - self.H2])

    @property
    def foot_rest(self):
        """Foot position (r, z) relative to the body CoM with the leg at rest [m]."""
        return self.joint_P + self.L_h0 * jnp.stack([jnp.cos(self.theta_b), -jnp.sin(self.theta_b)])

    @property
    def L_a0(self):
        """In-plane distance from the auxiliary joint to the foot at rest, |F0 - A| [m]."""
        return jnp.linalg.norm(self.foot_rest - self.joint_A)

    @property
    def L_a0_pair(self):
        """Rest length of each of the two auxiliary struts, joints at A +/- h laterally,
        sqrt(|F0 - A|^2 + h^2) [m] (derived: the leg is unstressed at rest)."""
        return jnp.sqrt(self.L_a0**2 + self.h**2)


class Ground(eqx.Module):
    """Foot-ground contact (paper section 2.2, Eqs 4-14, Table 2)."""

    k: jnp.ndarray = _param("N/m", "normal contact stiffness in compression (virgin loading)",
                            "paper Table 2", "> 0", toml="k_N_per_m")
    gamma: jnp.ndarray = _param(
        "1", "fraction of the stored normal energy lost per loading (restitution stiffness "
        "k / (1 - gamma); energetic restitution coefficient sqrt(1 - gamma))",
        "paper Table 2", "in [0, 1)", toml="gamma")
    chi: jnp.ndarray = _param("s/m", "normal contact damping, factor (1 + chi * d_dot)",
                              "paper Table 2", ">= 0", toml="chi_s_per_m")
    mu: jnp.ndarray = _param("1", "Coulomb friction coefficient foot-ground",
                             "paper Table 2", ">= 0", toml="mu")
    k_tan: jnp.ndarray = _param("N/m", "stiffness of each of the two tangential springs",
                                "paper Table 2", "> 0", toml="k_tan_N_per_m")

    @property
    def k_r(self):
        """Restitution (unloading) stiffness of the normal spring, k / (1 - gamma) [N/m]."""
        return self.k / (1.0 - self.gamma)


class Vehicle(eqx.Module):
    """The whole vehicle: masses, gravity, and one leg design shared by all legs."""

    m_body: jnp.ndarray = _param(
        "kg", "mass of the main body (incl. upper struts), m1", "paper section 3.1", "> 0",
        toml="m_body_kg")
    m_foot: jnp.ndarray = _param("kg", "mass of one foot with the lower main strut, m2",
                                 "paper section 3.1", "> 0", toml="m_foot_kg")
    g: jnp.ndarray = _param("m/s^2", "gravitational acceleration", "standard gravity",
                            "> 0", toml="g_mps2")
    I_xx: jnp.ndarray = _param(
        "kg m^2", "body roll inertia about its centre of mass (3-D model)",
        "our assumption: solid cylinder, radius R = 0.6 m (the paper's body radius), length "
        "3.2 m: m1 (3 R^2 + L^2) / 12", "> 0", toml="I_xx_kg_m2")
    I_yy: jnp.ndarray = _param(
        "kg m^2", "body pitch inertia about its centre of mass (3-D model)",
        "our assumption: as I_xx (axisymmetric body)", "> 0", toml="I_yy_kg_m2")
    I_zz: jnp.ndarray = _param(
        "kg m^2", "body yaw inertia about its axis (3-D model)",
        "our assumption: solid cylinder, m1 R^2 / 2 with R = 0.6 m", "> 0", toml="I_zz_kg_m2")
    leg: Leg = eqx.field(default=None)
    honeycomb: Honeycomb = eqx.field(default=None)
    ground: Ground = eqx.field(default=None)
    n_legs: int = eqx.field(static=True, default=4)

    @property
    def m_quarter(self):
        """Body mass carried by one leg in a symmetric landing, m1 / n_legs [kg]."""
        return self.m_body / self.n_legs
