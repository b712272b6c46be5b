"""The calibration problem: weighted residuals of the quarter model against drop-test traces.

For drop d, channel c and sample i inside the fit window,

    r_dci = (m_c(t_i - t0_d; p) - y_dci) / sigma_dc

where ``m_c`` is the quarter model's trajectory (``jaxland.landing``, started at touchdown with
the drop's touchdown speed, sampled every ``save_dt`` and linearly interpolated to the sample
times), ``y`` the offset-corrected data, ``sigma_dc`` the channel's noise estimate and ``t0_d``
the drop's touchdown time on the record's axis. A drop whose metadata names an SAE J211 CFC
filter has ``m_c`` and ``y`` both filtered (``_filter``; the model in JAX, so the Jacobian
runs through the filter; data the lab filtered already are not filtered twice), over a margin
beyond the window that keeps the backward pass's start out of it, and ``sigma_dc`` is the
filtered noise's std. Several legs' series of one channel are each compared with the same
quarter-model trace (a symmetric vertical drop). Before touchdown (t < t0) the model holds its
touchdown values (no force, no stroke, body acceleration -g), so the few samples before the
onset pin ``t0``.

The unknowns are ``theta = (z, dt0)``: the unconstrained model parameters ``z``
(``_parameters``) and one touchdown shift per drop in milliseconds from the detected touchdown.
The vehicle is built from ``z`` inside the jitted function; every parameter that is not fitted
stays a compile-time constant of the landing loop (several times faster on CPU).

With ``shared_forms`` the primary crush peak's form is a runtime argument instead
(``_parameters.forms_vehicle``): the compiled functions fit the form-independent parameter
list ``shared_names`` (the problem's, L_rise1 added where absent and placed last) and serve
the problem in each of ``PEAK_FORMS``, so the peak-shape refits of a fit (``model_form_spread``)
compile nothing. A problem whose form does not use L_rise1 holds that coordinate at 0 (the
middle of its bounds; the form ignores its value) and drops its Jacobian column.

With ``peak_site="forces"`` the primary crush peak sits on the force channels alone: the
landing runs without it, and the model's force channels are multiplied by
``force_channel_gain``, 1 + e(p) / F1, e the peak's excess over the plateau (in the problem's
form) at the crush p so far (from the crush's start on). The stroke and the body
acceleration are the drop's without the peak: a force the motion does not show, as a load
cell's artefact.

Every compiled function whose parameters hold peak1 switches the primary crush peak on or
off at run time (the first data argument): on for a problem that fits peak1, off for its
special case without the peak (``CalibrationProblem.without_peak``: the peak's coordinates
held in the slot, their Jacobian columns dropped, the peak ratio read as exactly 1, so that
the peak's height (r - 1) F1, its form's excess and the force channels' gain are 0, 0 and
1: no peak). So a fit with the peak and its check against the model without it
(``fit``'s no-peak check) share one compiled program. With ``peak_switch`` the peak is the
law's linear one (``PEAK_PARAMS``) and a problem without it runs on that switch too: the
compiled functions fit ``switch_names`` (the problem's list without PEAK_PARAMS, then
PEAK_PARAMS), so that a fit without the peak and its repetition with the peak (the
missing-peak term of ``fit``) share one compiled program.

The integrator is configurable (``integrator``, ``smoothing_m``, ``smoothing_N``: the
``jaxland.Solver`` fields ``method``, ``smoothing_m``, ``smoothing_N``), restricted to the
fixed-step methods; the compiled functions are keyed on all three.
"""

from __future__ import annotations

import copy
import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxland as jl
from jaxland import FIXED_STEP_METHODS

from ._data import CHANNELS, LEG_COLUMN, DropTest, base_channel
from ._filter import IDENTITY, filtfilt_jax, filtfilt_np, noise_gain, settle_time_s, white_lag1
from ._parameters import (
    EXP_TABLE_SPAN,
    FORCES,
    FORM_INDEX,
    HONEYCOMB,
    PEAK_FORMS,
    PEAK_PARAMS,
    RISE_FORMS,
    check_names,
    check_peak_site,
    forms_vehicle,
    from_unconstrained,
    no_peak_names,
    peak_form_vehicle,
    set_values,
    to_unconstrained,
)

__all__ = ["CalibrationProblem", "INTEGRATORS", "check_integrator", "shared_names",
           "switch_names"]

MS = 1e-3  # the touchdown shifts are fitted in milliseconds
SHARED = "shared"  # the compiled functions' peak form: every form, chosen at run time
SWITCH = "switch"  # the compiled functions' primary peak: the linear one, fitted or not
FORCE_CHANNELS = ("normal_force_N", "buffer_force_N")
PRIMARY_PEAK_FIELDS = ("peak_ratio1", "peak_rise1", "excess1")  # None: off
PLAIN = 1e150  # Huber threshold that never acts (plain least squares)
_COMPILED: dict = {}  # compiled residual/Jacobian functions, shared by problems of equal shape
# fixed-step methods only: the fit checks dt against their stability limit and samples the
# model on a fixed time grid (impulse and tsit5 choose their own steps)
INTEGRATORS = FIXED_STEP_METHODS


SAVE_DT = 2e-5  # s, the model's sampling interval, interpolated to the records' samples
WINDOW_MIN_S = 1e-3  # s, the shortest fit window after touchdown


def check_integrator(integrator, smoothing_m, smoothing_N) -> tuple[str, float, float]:
    """Validate the integrator settings; (method, smoothing_m, smoothing_N) as plain values.
    Errors name the field, the value and the rule."""
    if not isinstance(integrator, str) or integrator not in INTEGRATORS:
        raise jl.ConfigError("integrator", integrator,
                             "must be one of " + ", ".join(INTEGRATORS) + " (the fixed-step "
                             "methods; impulse and tsit5 choose their own steps)")
    out = []
    for name, val, unit in (("smoothing_m", smoothing_m, "m"), ("smoothing_N", smoothing_N,
                                                                 "N")):
        if isinstance(val, bool) or not isinstance(val, (int, float, np.floating)) or not (
                np.isfinite(val) and val >= 0):
            raise jl.ConfigError(name, val, f"must be a finite number >= 0 {unit} (0: hard "
                                 "switches)")
        out.append(float(val))
    return integrator, out[0], out[1]


def _vehicle_key(vehicle):
    leaves, treedef = jax.tree.flatten(vehicle)  # scalars, and tables (Honeycomb.excess1)
    return treedef, tuple(float(x) if np.ndim(x) == 0 else tuple(np.ravel(x).tolist())
                          for x in leaves)


def shared_names(names) -> tuple:
    """The parameter list of the compiled functions that serve every peak form
    (``shared_forms``): ``names`` without L_rise1, then L_rise1."""
    return tuple(n for n in names if n != "L_rise1") + ("L_rise1",)


def switch_names(names) -> tuple:
    """The parameter list of the compiled functions whose primary peak is switched at run time
    (``peak_switch``): ``names`` without PEAK_PARAMS, then PEAK_PARAMS."""
    return tuple(n for n in names if n not in PEAK_PARAMS) + PEAK_PARAMS


def _without_primary_peak(vehicle: jl.Vehicle) -> jl.Vehicle:
    """``vehicle`` with no primary crush peak (every other field, the secondary's peak
    included, kept; the unused table length at its default); jit-safe. A plain
    ``jaxland.Honeycomb``, also where the peak's form made it another kind."""
    hc = vehicle.honeycomb
    kw = {f.name: getattr(hc, f.name) for f in dataclasses.fields(jl.Honeycomb)}
    kw.update(dict.fromkeys(PRIMARY_PEAK_FIELDS),
              excess_length1=jl.Honeycomb.__dataclass_fields__["excess_length1"].default)
    return eqx.tree_at(lambda v: v.honeycomb, vehicle, jl.Honeycomb(**kw))


def force_channel_gain(vehicle: jl.Vehicle, plastic_set_m):
    """The force channels' gain 1 + e(p) / F1 of a primary crush peak that sits on the force
    channels (``peak_site="forces"``): e the peak's excess over the plateau in ``vehicle``'s
    form of it (``jaxland.laws.primary_peak_excess``) at the crush p [m] so far, the drop's
    permanent set, from the crush's start on (p > 0). A gain of the crush, not of the block's
    elastic line: 1 until the block starts to crush, then the peak's shape (a form that starts
    at its top jumps there), and 1 once the peak has decayed."""
    hc = vehicle.honeycomb.curve()
    excess = jl.laws.primary_peak_excess(plastic_set_m, hc)
    return 1.0 + jnp.where(plastic_set_m > 0.0, excess, 0.0) / hc.F1


def _compiled(vehicle, names, solver, channels, fit_t0, filtered=False, peak_form=None,
              peak_site=HONEYCOMB):
    """(residual_fn, jacobian_fn) for this vehicle, parameter selection, solver and channels
    (and whether a CFC filter acts, and the primary peak's form: None, the vehicle's own;
    SHARED, the form's code ``FORM_INDEX`` as a data argument; SWITCH, the vehicle's linear
    one, ``names`` being ``switch_names``; and where it sits, ``PEAK_SITES``); compiled once
    and shared (data, speeds, windows and filter coefficients are arguments). Where ``names``
    hold peak1 the first data argument switches the primary peak on or off (module
    docstring), before the form's code."""
    key = (_vehicle_key(vehicle), names, solver.dt, solver.t_end, solver.save_dt,
           solver.method, solver.smoothing_m, solver.smoothing_N, channels, fit_t0, filtered,
           peak_form, peak_site)
    if key in _COMPILED:
        return _COMPILED[key]
    model_cols = tuple(CHANNELS[base_channel(c)][1] for c in channels)
    on_forces = np.array([base_channel(c) in FORCE_CHANNELS for c in channels])
    n_z = len(names)
    switched = "peak1" in names

    def residual(theta, *args):
        if switched:
            on, *args = args
        if peak_form == SHARED:
            form, *args = args
        speeds, rel_t, data, inv_sigma, mask, huber_c, coeffs = args
        z = theta[:n_z]
        # the bounds of the primary peak's parameters depend on its form (the exp table's span)
        bounds_form = form if peak_form == SHARED else None if peak_form == SWITCH else peak_form
        veh = set_values(vehicle, names, from_unconstrained(z, names, vehicle, bounds_form,
                                                            peak_site))
        if switched:  # off: ratio exactly 1, the peak's height (r - 1) F1 is 0 in every form
            veh = eqx.tree_at(lambda v: v.honeycomb.peak_ratio1, veh,
                              jnp.where(on, veh.honeycomb.peak_ratio1, 1.0))
        if peak_form == SHARED:
            veh = forms_vehicle(veh, form)
        elif peak_form not in (None, SWITCH):
            veh = peak_form_vehicle(veh, peak_form)
        scenes = jl.Scene.batch(drop_height=0.0, sink_speed=speeds)
        if peak_site == FORCES:  # the drop without the peak; the peak on the force channels
            traj, summary = jl.landings(_without_primary_peak(veh), scenes, solver, "quarter")
            gain = force_channel_gain(veh, traj["plastic_set_m"])  # (drops, saves)
        else:
            traj, summary = jl.landings(veh, scenes, solver, "quarter")
        shift = theta[n_z:] * MS if fit_t0 else jnp.zeros_like(speeds)
        tau = rel_t - shift[:, None]  # (drops, samples): model time of each sample

        def one(tm, ys, ta):  # one drop: (saves,), (channels, saves), (samples,)
            return jax.vmap(lambda y: jnp.interp(ta, tm, y))(ys)

        ys = jnp.stack([traj[c] for c in model_cols], axis=1)  # (drops, channels, saves)
        if peak_site == FORCES:
            ys = jnp.where(on_forces[None, :, None], ys * gain[:, None, :], ys)
        model = jax.vmap(one)(traj["time_s"], ys, tau)  # (drops, channels, samples)
        if filtered:  # SAE J211, as on the data (identity rows for unfiltered series)
            model = filtfilt_jax(model, coeffs)
        r = ((model - data) * inv_sigma[:, :, None] * mask).ravel()
        # Huber: r -> sign(r) c sqrt(2|r|/c - 1) beyond c, so 0.5 r^2 becomes c|r| - c^2/2
        u = jnp.abs(r) / huber_c
        u_safe = jnp.where(u <= 1.0, 1.0, u)
        r = jnp.where(u <= 1.0, r, jnp.sign(r) * huber_c * jnp.sqrt(2.0 * u_safe - 1.0))
        return r, jnp.any(summary["failed"])

    res_jit = jax.jit(residual)

    def with_jac(theta, *args):
        def f(th):  # the jitted residual: its trace is reused (``compile``), its code the same
            r, failed = res_jit(th, *args)
            return r, (r, failed)

        jac, (r, failed) = jax.jacfwd(f, has_aux=True)(theta)
        return r, jac, failed

    fns = (res_jit, jax.jit(with_jac))
    _COMPILED[key] = fns
    return fns


class CalibrationProblem:
    """Weighted least squares of the quarter model against one or more drop tests.

    Parameters
    ----------
    drops : list of DropTest
    params : names of the fitted parameters (``calibration.PARAMS``)
    vehicle : the vehicle whose other parameters stay fixed (default: the first drop's)
    window_s : fit window after each drop's detected touchdown [s]
    pre_s : samples this long before the detected touchdown are included [s] (they pin t0)
    dt, save_dt : integration step and model sampling interval [s]
    integrator : ``jaxland.Solver.method``, one of ``INTEGRATORS`` (default ``"euler"``)
    smoothing_m, smoothing_N : ``jaxland.Solver`` switch-smoothing widths [m], [N] (default 0:
        hard switches)
    fit_touchdown : fit one touchdown-time shift per drop (else use the detected touchdown)
    channels : channels to fit (default: every channel any drop has)
    peak_form : the primary crush peak's form (``PEAK_FORMS``; None: the vehicle's own law).
        ``exp`` reads peak1 and L_peak1 as an exponential peak's height and decay length,
        ``rise_exp`` too, built up linearly over L_rise1 first, ``smooth_exp`` built up
        smoothly (``_parameters.smooth_table``)
    shared_forms : compile functions that serve every peak form (module docstring), shared
        with the problems of the same drops in the other forms; needs peak1 among ``params``.
        The form is then ``peak_form`` (one of ``RISE_FORMS`` with L_rise1 among
        ``params``), or None: ``rise`` with L_rise1 among ``params``, else ``linear``
    peak_switch : compile functions whose primary crush peak (the law's linear one) is
        switched on or off at run time (module docstring), shared with the problem of the
        same drops with the peak fitted (PEAK_PARAMS among ``params``: on) or not (off; the
        vehicle must then have no primary peak)
    peak_site : where the primary crush peak sits (``PEAK_SITES``): ``"honeycomb"`` (default:
        the law's) or ``"forces"``, the force channels alone (the drop runs without the peak,
        and the force channels are multiplied by ``force_channel_gain``); needs peak1 among
        ``params``, not with ``peak_switch``
    """

    def __init__(self, drops: list[DropTest], params=None, *, vehicle: jl.Vehicle | None = None,
                 window_s: float = 0.1, pre_s: float = 0.005, dt: float = 1e-5,
                 save_dt: float = SAVE_DT, integrator: str = "euler", smoothing_m: float = 0.0,
                 smoothing_N: float = 0.0, fit_touchdown: bool = True, channels=None,
                 peak_form: str | None = None, shared_forms: bool = False,
                 peak_switch: bool = False, peak_site: str = HONEYCOMB):
        from ._parameters import DEFAULT_PARAMS

        if peak_form is not None and peak_form not in PEAK_FORMS:
            raise jl.ConfigError("peak_form", peak_form, "must be one of "
                                 + ", ".join(PEAK_FORMS))
        if isinstance(drops, DropTest):
            drops = [drops]
        drops = list(drops)
        if not drops:
            raise jl.ConfigError("drops", "[]", "give at least one drop test")
        self.drops = drops
        self.names = check_names(DEFAULT_PARAMS if params is None else params)
        self.shared_forms = bool(shared_forms)
        if self.shared_forms:
            if "peak1" not in self.names:
                raise jl.ConfigError("shared_forms", shared_forms, "needs peak1 among the "
                                     "fitted parameters (it shares the crush peak's forms)")
            rise = "L_rise1" in self.names
            if peak_form is None:
                peak_form = "rise" if rise else "linear"
            if rise != (peak_form in RISE_FORMS):
                raise jl.ConfigError("peak_form", peak_form, "the built-up forms ("
                                     + ", ".join(RISE_FORMS) + "), and only they, fit L_rise1")
        self.peak_form = peak_form
        check_peak_site(peak_site, self.names)
        if peak_site == FORCES and peak_switch:
            raise jl.ConfigError("peak_site", peak_site, "the peak on the force channels is "
                                 "fitted (peak1): not with peak_switch")
        self.peak_site = peak_site
        self.vehicle = drops[0].vehicle if vehicle is None else vehicle
        # a peak on the force channels is no honeycomb's: the honeycomb's rules for its peak
        # do not bind it (its own bounds: ``_parameters._gain_bounds``)
        jl.validate_vehicle(_without_primary_peak(self.vehicle) if peak_site == FORCES
                            else self.vehicle)
        self.peak_switch = bool(peak_switch)
        self.peak_on = "peak1" in self.names  # (with peak_switch: all of PEAK_PARAMS, checked)
        if self.peak_switch:
            hc = self.vehicle.honeycomb
            if self.shared_forms or peak_form is not None or "L_rise1" in self.names:
                raise jl.ConfigError("peak_switch", peak_switch, "switches the law's linear "
                                     "peak only: not with shared_forms, peak_form or L_rise1")
            if hc.peak_rise1 is not None or hc.excess1 is not None:
                raise jl.ConfigError("peak_switch", peak_switch, "switches the law's linear "
                                     "peak only: the vehicle's primary peak has "
                                     + ("a rise (peak_rise1)" if hc.peak_rise1 is not None
                                        else "an exponential table (excess1)"))
            if any(n in self.names for n in PEAK_PARAMS) != all(n in self.names
                                                                 for n in PEAK_PARAMS):
                raise jl.ConfigError("peak_switch", peak_switch, "needs all of "
                                     + ", ".join(PEAK_PARAMS) + " among the fitted "
                                     "parameters or none")
            if not self.peak_on and hc.peak_ratio1 is not None:  # (rise, table: refused above)
                raise jl.ConfigError("peak_switch", peak_switch, "switched off, it would "
                                     "remove the vehicle's own primary crush peak")
        for name, val, least in (("window_s", window_s, WINDOW_MIN_S), ("pre_s", pre_s, 0.0)):
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not (
                    np.isfinite(val) and val >= least):
                raise jl.ConfigError(name, val, f"must be a finite number >= {least:g} s")
        for d in drops:
            if d.duration_after_touchdown_s < window_s - 0.5 / d.sample_rate_Hz:
                raise jl.ConfigError("window_s", window_s, f"longer than the record "
                                     f"{d.name} after touchdown "
                                     f"({d.duration_after_touchdown_s:.4g} s)")
        self.window_s, self.pre_s = float(window_s), float(pre_s)
        self.fit_touchdown = bool(fit_touchdown)
        present = sorted({c for d in drops for c in d.channels},
                         key=lambda c: (list(CHANNELS).index(base_channel(c)),
                                        LEG_COLUMN.match(c) is not None, c))
        if channels is None:
            channels = present
        channels = tuple(channels)
        for c in channels:
            if c not in present:
                raise jl.ConfigError("channels", c, "not in the data; present: "
                                     + ", ".join(present))
        if not channels:
            raise jl.ConfigError("channels", "", "select at least one channel")
        self.channels = channels
        # a CFC filter: the model is filtered over margin_s beyond the window too, so the
        # backward pass's start leaves no trace inside the window (``_filter.settle_time_s``)
        cfcs = [d.filters[c] for d in drops for c in channels if c in d.filters]
        self.filtered = bool(cfcs)
        self.margin_s = max((settle_time_s(c) for c in cfcs), default=0.0)
        # model time span: the window plus room for the touchdown shift
        method, smoothing_m, smoothing_N = check_integrator(integrator, smoothing_m,
                                                            smoothing_N)
        self.integrator = method
        self.solver = jl.Solver(dt=dt, t_end=self.window_s + self.margin_s + 0.005,
                                save_dt=save_dt,
                                method=method, smoothing_m=smoothing_m,
                                smoothing_N=smoothing_N)
        self.solver.validate()
        n = max(int(np.sum(self._in_window(d))) for d in drops)
        nd, nc = len(drops), len(channels)
        rel_t = np.zeros((nd, n))
        data = np.zeros((nd, nc, n))
        mask = np.zeros((nd, nc, n))
        inv_sigma = np.ones((nd, nc))
        offset_var = np.zeros((nd, nc))  # variance of each offset, in residual units
        gain_sd = np.zeros((nd, nc))  # standard uncertainty of each gain, relative
        gain_zero = np.zeros((nd, nc))  # the datum a gain error leaves as it is
        coeffs = np.tile(IDENTITY, (nd, nc, 1))
        for i, d in enumerate(drops):
            sel = self._in_window(d)
            m = int(np.sum(sel))
            rel_t[i, :m] = d.time_s[sel] - d.touchdown_time_s
            rel_t[i, m:] = rel_t[i, m - 1] if m else 0.0
            inside = rel_t[i, :m] <= self.window_s + 1e-12
            corr = d.corrected
            for j, c in enumerate(channels):
                if c in d.channels:
                    coeffs[i, j] = d.filter_coefficients(c)
                    y = corr[c]
                    gain = 1.0
                    if c in d.filters and not d.filter_data_prefiltered:
                        y, gain = filtfilt_np(y, coeffs[i, j]), noise_gain(coeffs[i, j])
                    data[i, j, :m] = y[sel]
                    mask[i, j, :m] = inside
                    inv_sigma[i, j] = 1.0 / (d.noise_std[c] * gain)
                    gain_sd[i, j] = d.gain_uncertainty_rel.get(c, 0.0)
                    gain_zero[i, j] = d.gain_reference(c)
                    if d.offset_samples and c not in d.filters:
                        # the mean of n samples of white noise: sigma^2 / n (a filtered
                        # channel's noise is correlated: left out, its errors are HAC's)
                        offset_var[i, j] = 1.0 / d.offset_samples
        self.offset_var, self.gain_sd, self.gain_zero = offset_var, gain_sd, gain_zero
        self.coeffs = coeffs
        # lag-1 autocorrelation that filtered white noise has (0 unfiltered): the misfit
        # test reads the residuals' autocorrelation against it
        self.noise_lag1 = max((white_lag1(coeffs[i, j]) for i in range(nd)
                               for j in range(nc)), default=0.0)
        self.speeds = np.array([d.touchdown_speed_mps for d in drops])
        self.rel_t, self.data, self.inv_sigma = rel_t, data, inv_sigma
        self.has, self.mask = mask, mask
        self.n_obs = int(mask.sum())
        self.active_window_s = self.window_s
        self.huber_c = PLAIN
        self.n_z = len(self.names)
        self.n_theta = self.n_z + (nd if self.fit_touchdown else 0)
        # the fitted values are replaced inside: key the compiled code on the fixed ones only
        # (the problems of one fit in every peak form share the functions of shared_names,
        # those with the peak switched on and off the functions of switch_names)
        self._z_names = (shared_names(self.names) if self.shared_forms
                         else switch_names(self.names) if self.peak_switch else self.names)
        self._canonical = set_values(self.vehicle, self._z_names,
                                     np.full(len(self._z_names), 0.5))
        self._fns = _compiled(self._canonical, self._z_names, self.solver, channels,
                              self.fit_touchdown, self.filtered,
                              SHARED if self.shared_forms else SWITCH if self.peak_switch
                              else peak_form, peak_site)
        self._res_jit = self._fns[0]
        self._bind()

    def _bind(self) -> None:
        """This problem's residual and Jacobian functions on the compiled ones (``_fns``)."""
        fns = self._fns
        if self._z_names == self.names:
            self._res, self._jac = fns
            self._embed, self._z_cols = (lambda theta: theta), slice(None)
            self._z_src = np.arange(self.n_z)
            return
        # theta -> the shared functions' theta: each coordinate from its place in theta, the
        # coordinates this problem does not fit (the rise in a form without one, the peak
        # switched off) from the slot appended after theta (held at 0); their Jacobian's
        # columns back in theta's order
        names_u, n_s = self._z_names, self.n_theta - self.n_z
        n_u = len(names_u)
        src = np.array([self.names.index(n) if n in self.names else self.n_theta
                        for n in names_u] + [self.n_z + k for k in range(n_s)])
        cols = np.array([names_u.index(n) for n in self.names] + [n_u + k for k in range(n_s)])
        self._z_cols, self._z_src = cols[:self.n_z], src[:n_u]
        res_u, jac_u = fns

        def embed(theta):  # numpy where theta is known (no small programs to compile)
            if isinstance(theta, jax.core.Tracer):
                return jnp.concatenate([theta, jnp.zeros(1, theta.dtype)])[src]
            return jnp.asarray(np.append(np.asarray(theta, dtype=float), 0.0)[src])

        def res(theta, *args):
            return res_u(embed(theta), *args)

        def jac(theta, *args):
            r, j, failed = jac_u(embed(theta), *args)
            j = j[:, cols] if isinstance(j, jax.core.Tracer) else np.asarray(j)[:, cols]
            return r, j, failed

        self._res, self._jac, self._embed = res, jac, embed

    @property
    def peak_switches_off(self) -> bool:
        """Whether the compiled functions switch the primary crush peak off to the model
        without it (``without_peak``): they fit peak1, and the vehicle holds no tabulated
        excess (``Honeycomb.excess1``) that the peak's form leaves in place (the shared
        forms and the tabulated ones build theirs from peak1; the law's forms keep the
        vehicle's)."""
        return "peak1" in self._z_names and (
            self._canonical.honeycomb.excess1 is None or self.shared_forms
            or self.peak_form in EXP_TABLE_SPAN)

    def without_peak(self, vehicle: jl.Vehicle | None = None) -> CalibrationProblem:
        """The problem's special case without the primary crush peak, on the same compiled
        functions (``peak_switches_off``), which it compiles nothing for: the parameters
        without the peak's (``SHAPE_PARAMS``; theta their coordinates, then the touchdown
        shifts), the peak switched off at run time. ``vehicle`` (default: the problem's)
        gives the start values, without its primary peak; its fixed values must be the
        problem's."""
        if not self.peak_switches_off:
            raise jl.ConfigError("peak_switch", False, "the compiled functions cannot switch "
                                 "the primary crush peak off: they do not fit peak1, or the "
                                 "vehicle's tabulated peak (excess1) stays in their form")
        names = no_peak_names(self.names)
        if not names:
            raise jl.ConfigError("params", ",".join(self.names), "only the crush peak's "
                                 "parameters: the model without the peak fits nothing")
        veh = _without_primary_peak(self.vehicle if vehicle is None else vehicle)
        half = np.full(len(names), 0.5)
        if _vehicle_key(set_values(veh, names, half)) != _vehicle_key(
                set_values(_without_primary_peak(self.vehicle), names, half)):
            raise jl.ConfigError("vehicle", "the one given", "its fixed values must be the "
                                 "problem's, which its compiled functions hold")
        new = copy.copy(self)
        new.__dict__.pop("_args_cache", None)
        new.names, new.vehicle, new.peak_on = names, jl.validate_vehicle(veh), False
        new.n_z = len(names)
        new.n_theta = new.n_z + (self.n_theta - self.n_z)
        new._bind()
        return new

    def windowed(self, window_s: float, channels=None, drops=None) -> CalibrationProblem:
        """The same problem (same compiled functions) fitting only the samples up to
        ``window_s`` after touchdown (<= the problem's ``window_s``), and only ``channels``
        (default: all of the problem's) of the drops at the indices ``drops`` (default: all;
        a drop left out keeps its touchdown coordinate, which no residual then moves)."""
        if not 0.0 < window_s <= self.window_s + 1e-12:
            raise jl.ConfigError("window_s", window_s,
                                 f"must be in (0, {self.window_s:g}] s (the problem's window)")
        new = copy.copy(self)
        new.mask = self.has * (self.rel_t <= window_s + 1e-12)[:, None, :]
        if channels is not None:
            keep = np.array([c in channels for c in self.channels], dtype=float)
            new.mask = new.mask * keep[None, :, None]
        if drops is not None:
            keep = np.array([i in drops for i in range(len(self.drops))], dtype=float)
            new.mask = new.mask * keep[:, None, None]
        new.n_obs = int(new.mask.sum())
        new.active_window_s = float(window_s)
        return new

    def robust(self, c: float | None) -> CalibrationProblem:
        """The same problem with a Huber loss of threshold ``c`` (weighted-residual units;
        None: plain least squares)."""
        new = copy.copy(self)
        new.huber_c = PLAIN if c is None else float(c)
        return new

    def _in_window(self, d: DropTest) -> np.ndarray:
        """The samples of the problem's grid: the window, and the filter's margin beyond."""
        rel = d.time_s - d.touchdown_time_s
        return (rel >= -self.pre_s) & (rel <= self.window_s + self.margin_s + 1e-12)

    # ------------------------------------------------------------------------ parameters
    def theta_from(self, vehicle: jl.Vehicle | None = None, shifts_ms=None) -> np.ndarray:
        """theta for ``vehicle``'s values of the fitted parameters (default: the problem's
        vehicle) and touchdown shifts (default 0)."""
        z = to_unconstrained(self.vehicle if vehicle is None else vehicle, self.names,
                             self.peak_form, self.peak_site)
        if not self.fit_touchdown:
            return z
        s = np.zeros(len(self.drops)) if shifts_ms is None else np.asarray(shifts_ms, float)
        return np.concatenate([z, s])

    def _transform(self, jacobian: bool = False):
        """The jitted (z, form code) -> values (or their Jacobian in z) of the compiled
        functions' parameters, shared by the problems with the same fixed values (the fitted
        ones are not read) and peak form (with ``shared_forms``, every form: its code is read)."""
        form = SHARED if self.shared_forms else self.peak_form
        site = self.peak_site
        key = ("values", _vehicle_key(self._canonical), self._z_names, jacobian, form, site)
        if key not in _COMPILED:
            names, vehicle = self._z_names, self._canonical

            def f(z, code):
                return from_unconstrained(z, names, vehicle, code if form == SHARED else form,
                                          site)

            _COMPILED[key] = jax.jit(jax.jacfwd(f) if jacobian else f)
        return _COMPILED[key]

    @property
    def _peak_off(self) -> bool:
        """The primary peak switched off in the compiled functions (``without_peak``, or a
        problem without the peak on ``peak_switch``'s)."""
        return "peak1" in self._z_names and not self.peak_on

    def _z(self, theta) -> np.ndarray:
        """The compiled functions' parameter coordinates at ``theta`` (numpy)."""
        return np.append(np.asarray(theta, dtype=float), 0.0)[self._z_src]

    def _code(self) -> int:
        """The peak form's code (``FORM_INDEX``) that the shared functions read; 0 otherwise."""
        return FORM_INDEX[self.peak_form] if self.shared_forms else 0

    def values(self, theta) -> np.ndarray:
        """Physical values of the fitted parameters [SI] at ``theta``."""
        return np.asarray(self._transform()(self._z(theta), self._code()))[self._z_cols]

    def vehicle_at(self, theta) -> jl.Vehicle:
        """The vehicle with the fitted parameters at ``theta``, its peak in the problem's
        form (validated); without the primary peak where it sits on the force channels."""
        veh = set_values(self.vehicle, self.names, self.values(theta))
        if self.peak_site == FORCES:
            return jl.validate_vehicle(_without_primary_peak(veh))
        if self.peak_form is not None and not self._peak_off:
            veh = peak_form_vehicle(veh, self.peak_form)
        return jl.validate_vehicle(veh)

    def touchdown_times(self, theta) -> np.ndarray:
        """Each drop's touchdown time on its record's axis [s] at ``theta``."""
        t0 = np.array([d.touchdown_time_s for d in self.drops])
        if self.fit_touchdown:
            t0 = t0 + np.asarray(theta[self.n_z:]) * MS
        return t0

    def transform_jacobian(self, theta) -> np.ndarray:
        """d(physical values)/d(theta[:n_z]) (for the delta method)."""
        g = np.asarray(self._transform(jacobian=True)(self._z(theta), self._code()))
        return g[self._z_cols][:, self._z_cols]

    # ------------------------------------------------------------------------ evaluation
    def _args(self):
        """The compiled functions' data arguments, on the device once per mask and loss."""
        cached = self.__dict__.get("_args_cache")
        if cached is not None and cached[0] is self.mask and cached[1] == self.huber_c:
            return cached[2]
        args = (jnp.asarray(self.speeds), jnp.asarray(self.rel_t), jnp.asarray(self.data),
                jnp.asarray(self.inv_sigma), jnp.asarray(self.mask),
                jnp.asarray(self.huber_c, dtype=jnp.float64), jnp.asarray(self.coeffs))
        if self.shared_forms:  # the peak's form, an argument of the shared functions
            args = (jnp.asarray(self._code(), dtype=jnp.int32), *args)
        if "peak1" in self._z_names:  # the peak on or off, an argument of such functions
            args = (jnp.asarray(self.peak_on), *args)
        self._args_cache = (self.mask, self.huber_c, args)
        return args

    def compile(self, theta) -> None:
        """Compile (or find compiled) both functions for this problem's shapes: the residual's
        in a second thread while the Jacobian's compiles here (XLA compiles without the
        interpreter lock: on two cores the residual's compilation then costs no wall time),
        and after it, in that thread, the transforms of ``values`` and
        ``transform_jacobian``, which every fit reads (otherwise compiled on its way)."""
        import threading

        th = jnp.asarray(theta, dtype=jnp.float64)
        args = self._args()

        def second():
            self._res(th, *args)[0].block_until_ready()
            self.values(theta)
            self.transform_jacobian(theta)

        # the residual traced here first: the Jacobian's trace then reuses its jaxpr instead
        # of tracing the landing again, while the residual compiles in the second thread
        self._res_jit.trace(self._embed(th), *args)
        side = threading.Thread(target=second)
        side.start()
        try:
            self._jac(th, *args)[0].block_until_ready()
        finally:
            side.join()

    def residuals(self, theta) -> tuple[np.ndarray, bool]:
        """Weighted residual vector (flattened drops x channels x samples; padding is 0) and
        whether any landing failed numerically."""
        r, failed = self._res(jnp.asarray(theta, dtype=jnp.float64), *self._args())
        return np.asarray(r), bool(failed)

    def residuals_and_jacobian(self, theta):
        """(r, J, failed) with J = dr/dtheta by forward mode (``jax.jacfwd``)."""
        r, jac, failed = self._jac(jnp.asarray(theta, dtype=jnp.float64), *self._args())
        return np.asarray(r), np.asarray(jac), bool(failed)

    def loss(self, theta) -> float:
        """0.5 * sum of squared weighted residuals."""
        r, _ = self.residuals(theta)
        return 0.5 * float(r @ r)

    def loss_fn(self):
        """A pure, jittable ``theta -> loss`` (for ``jax.grad`` / ``jax.jacfwd``)."""
        args = self._args()
        res = self._res

        def f(theta):
            r, _ = res(theta, *args)
            return 0.5 * jnp.sum(r * r)

        return f

    def channel_rms(self, theta) -> dict:
        """Per drop and channel: RMS of the unweighted residual (data units)."""
        r, _ = self.robust(None).residuals(theta)
        r = r.reshape(self.data.shape) / self.inv_sigma[:, :, None]
        out = {}
        for i, d in enumerate(self.drops):
            out[d.name] = {}
            for j, c in enumerate(self.channels):
                m = self.mask[i, j] > 0
                if m.any():
                    out[d.name][c] = float(np.sqrt(np.mean(r[i, j, m] ** 2)))
        return out
