"""The integrator contract, the run settings and the result codes.

An integrator is an ``eqx.Module`` subclass of ``AbstractIntegrator`` (as diffrax's solvers
subclass ``AbstractSolver``) holding its own options, static because they choose code and loop
lengths. It states its stability limit from the model's ``Oscillator`` and runs a landing of
any model whose capabilities it needs (``check_model``). ``Solver`` holds what every method
shares: the step, the duration, the output interval, the switch smoothing, and the integrator.
"""

from __future__ import annotations

import abc
import enum
import math
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.extend.core
import jax.interpreters.ad as ad
import jax.interpreters.batching as batching
import jax.interpreters.mlir as mlir
import numpy as np
from jaxtyping import Array

from .._checks import _is_number, as_number, at_most, check_int_size, named_as
from .._errors import ConfigError
from .._models import AbstractModel, Oscillator, Smoothing

SAVE_DT_MIN = 1e-4  # s: the default output interval is the smallest multiple of dt above this
T_END_MAX = 100.0  # s, longest simulated duration
SAVES_MAX = 1_000_000  # most saved samples of one landing (a trajectory of ~40 columns)
MAX_STEPS = 5e8  # steps a run may take (t_end / dt)
N_EVENTS = 256  # default capacity of the contact on/off log (later changes are counted)
# a switch width is a rounding only where it is small against what it rounds: at most this
# share of the vehicle's shortest switched length and of its first plateau force
SMOOTHING_SHARE = 0.1


class Result(enum.IntEnum):
    """How a landing ended. Carried per landing (per batch element) as an int32 code in the
    summary's ``result``; an ``IntEnum`` rather than an ``eqx.Enumeration`` because the codes
    leave the compiled program as numpy arrays (a Monte Carlo has 10^5 of them) and are named
    on the host."""

    SUCCESSFUL = 0
    NONFINITE = 1
    CLOSURE = 2
    STEP_ABOVE_LIMIT = 3
    OUTSIDE_ENVELOPE = 4
    LEDGER = 5
    SOLVER_STOPPED = 6
    NO_TOUCHDOWN = 7
    UNFINISHED = 8
    INVALID_VEHICLE = 9

    @property
    def message(self) -> str:
        return _MESSAGES[self]

    @property
    def failed(self) -> bool:
        """The landing's numbers are not to be used. A landing without touchdown, or one that
        t_end cut off during an impact, is no failure (its trajectory is what the model
        computes), but its outcomes are no landing's either: statistics count it apart."""
        return int(self) in FAILED_CODES


# the codes whose numbers are not to be used (Result.failed), as plain ints for array tests
FAILED_CODES = tuple(int(r) for r in Result
                     if r not in (Result.SUCCESSFUL, Result.NO_TOUCHDOWN, Result.UNFINISHED))

# |ledger residual| above this fraction of the landing's energy scale during the run: failure
ENERGY_TOLERANCE = 0.1
# Largest energy-ledger error, relative to the energy dissipated, accepted from a landing: at the
# default dt the paper drop closes to 7e-5; a step near the stability limit gives ~0.3.
CLOSURE_LIMIT = 1e-2

_MESSAGES = {
    Result.SUCCESSFUL: "the landing ran to its end",
    Result.NONFINITE: "non-finite state during the run",
    Result.LEDGER: f"energy ledger off by more than {ENERGY_TOLERANCE * 100:g} % of the landing's "
                   "energy during the run",
    Result.SOLVER_STOPPED: "the adaptive solver stopped early (max_steps reached, or the step "
                           "size collapsed at a discontinuity)",
    Result.NO_TOUCHDOWN: "no foot touched the ground before t_end",
    Result.CLOSURE: f"energy ledger did not close to {CLOSURE_LIMIT * 100:g} % of the energy "
                    "dissipated (step too large for this landing)",
    Result.STEP_ABOVE_LIMIT: "step above the stability limit of the forces the landing reached",
    Result.OUTSIDE_ENVELOPE: "scene outside the documented envelope, or asymmetric for the "
                             "quarter model (not simulated as valid)",
    Result.INVALID_VEHICLE: "a vehicle parameter outside its rule (not simulated as valid; "
                            "jaxland.validate_vehicle names it)",
    Result.UNFINISHED: "t_end came during an impact (a leg on the ground still compressing at "
                       "its largest stroke) or while the vehicle still had the energy to tip "
                       "over: the max stroke, the peaks or the tip-over are not final",
}


def positive(owner: str, name: str, val, unit: str, *, zero_ok: bool = False) -> None:
    """Refuse a setting that is not a finite number > 0 (>= 0 with ``zero_ok``)."""
    check_int_size(f"{owner}.{name}", val)
    ok = _is_number(val) and (val >= 0 if zero_ok else val > 0)
    if not ok:
        raise ConfigError(f"{owner}.{name}", val,
                          f"must be a finite number {'>=' if zero_ok else '>'} 0{unit}")


class AbstractIntegrator(eqx.Module):
    """A time-stepping method (see the module docstring)."""

    name: ClassVar[str]
    stability_reason: ClassVar[str]  # what sets its stability limit, for messages
    # dt is only the first step's size (an adaptive method): a run shorter than it may as well
    # want a smaller dt, and the refusal says so
    dt_is_first_step: ClassVar[bool] = False

    def validate(self) -> AbstractIntegrator:
        """Its options, each on its own; raises ``ConfigError`` naming the field."""
        return self

    def check_model(self, model: AbstractModel) -> None:
        """Refuse a model that lacks what this method needs."""

    @abc.abstractmethod
    def stable_step(self, osc: Oscillator) -> Array:
        """The largest stable step [s] for the model's stiffest, lightest oscillator."""

    @abc.abstractmethod
    def integrate(self, model: AbstractModel, vehicle, scene, solver: Solver):
        """One landing: ``(trajectory, summary)`` dicts of arrays (``jaxland._solvers._loop``).
        Pure and jittable."""

    @property
    def differentiable(self) -> bool:
        """Whether AD through it gives the derivative of the computed landing."""
        return True

    def options(self) -> dict:
        """Its options by name, for reports."""
        return {f: getattr(self, f) for f in self.__dataclass_fields__}


def _as_integrator(method):
    from ._names import integrator

    return integrator(method) if isinstance(method, str) else method


class Solver(eqx.Module):
    """Run settings shared by every integrator (static: they set loop lengths and choose code).

    ``method`` is an integrator (``Euler()``, ``EulerImplicit()``, ``Verlet()``,
    ``Leapfrog()``, ``Impulse(dI=...)``, ``Tsit5(rtol=..., atol=...)``) or its name for the
    defaults. ``jaxland.landing`` checks the settings (``validate``) before it runs.
    ``save_dt=None`` is the smallest whole multiple of ``dt`` that is at least 1e-4 s (or
    the largest that fits in a shorter ``t_end``).
    """

    dt: float = eqx.field(static=True, default=1e-5)  # s, step (impulse: cap; tsit5: first)
    t_end: float = eqx.field(static=True, default=1.2)  # s, simulated duration
    save_dt: float | None = eqx.field(static=True, default=None)  # s, output interval
    method: AbstractIntegrator = eqx.field(static=True, default="euler",
                                           converter=_as_integrator)
    # opt-in smoothing of the force-law switches, for gradient quality in fits (jaxland._laws.
    # _smooth; benchmarks/gradient_quality.py): width of the rounded kinks in length [m] (ground
    # contact, honeycomb unloading, stick/slip, top-out) and in force [N] (the strut's no-pull
    # floor). 0 (default) = the hard switches.
    smoothing_m: float = eqx.field(static=True, default=0.0)
    smoothing_N: float = eqx.field(static=True, default=0.0)
    # stop once no outcome can change any more (jaxland._solvers._settle); only for a run
    # without a trajectory (save_dt = t_end) of a fixed-step method. The summary then gains
    # settled_time_s; t_end_s is the time reached. Off by default: simulate runs to t_end.
    early_stop: bool = eqx.field(static=True, default=False)
    # the running maxima to keep (names of the model's ``peak_values``; the verdict's and the
    # early-stop bound's, ``_loop.ALWAYS_KEPT``, are kept too); None: all. Each kept peak is a
    # maximum taken on every step: a Monte Carlo keeps only those it reports.
    peaks: tuple[str, ...] | None = eqx.field(static=True, default=None,
                                              converter=lambda x: None if x is None else
                                              tuple(x))
    # check the energy ledger and the state's finiteness on every ``ledger_every``-th step
    # (fixed-step methods): the summary's ledger residual is then the worst over the checked
    # steps, and a failure is found at the first check after it. 1 (default): every step.
    ledger_every: int = eqx.field(static=True, default=1)
    # capacity of the summary's contact on/off log, event_times_s (0: only the changes are
    # counted, n_contact_changes; a Monte Carlo reports no event times)
    event_log: int = eqx.field(static=True, default=N_EVENTS)
    # False: no state is saved (the trajectory is an empty dict; the summary is the same, bit
    # for bit): a run that discards its trajectory (a Monte Carlo, a design) then does not
    # trace and lower the saved states' evaluation that XLA would remove (a 3-D Monte Carlo
    # chunk traces and lowers in about 0.8 of the time; the compiled program is the same)
    trajectory: bool = eqx.field(static=True, default=True)

    def __post_init__(self):
        # a concrete 0-d array as the number it holds (the fields are static)
        for name in ("dt", "t_end", "save_dt", "smoothing_m", "smoothing_N"):
            setattr(self, name, as_number(getattr(self, name)))
        if self.save_dt is None and _finite_positive(self.dt) and _steps_fit(SAVE_DT_MIN,
                                                                              self.dt):
            every = max(1, math.ceil(SAVE_DT_MIN / self.dt - 1e-9))
            if _finite_positive(self.t_end) and _steps_fit(self.t_end, self.dt):
                # a run shorter than that saves at its end
                every = min(every, max(1, math.floor(self.t_end / self.dt + 1e-9)))
            self.save_dt = self.dt * every

    @property
    def save_every(self) -> int:
        return max(1, int(round(self.save_dt / self.dt)))

    @property
    def n_saves(self) -> int:
        # whole save intervals to reach t_end; one that t_end fills to rounding (a step of
        # 1e-4/13 s saves every 9.999999999999999e-05 s) is not one more interval
        interval = self.dt * self.save_every
        ratio = self.t_end / interval
        return int(round(ratio)) if _whole_steps(self.t_end, interval) else int(math.ceil(ratio))

    @property
    def n_steps(self) -> int:
        return self.n_saves * self.save_every

    @property
    def smoothing(self) -> Smoothing:
        return Smoothing(float(self.smoothing_m), float(self.smoothing_N))

    def validate_values(self) -> Solver:
        """Each setting on its own."""
        for name in ("smoothing_m", "smoothing_N"):
            positive("solver", name, getattr(self, name), f" {name[-1]}", zero_ok=True)
        for name in ("dt", "t_end"):
            positive("solver", name, getattr(self, name), " s")
        if self.t_end > T_END_MAX:
            raise ConfigError("solver.t_end", self.t_end, f"must be <= {T_END_MAX:g} s (a "
                              "landing settles within seconds)")
        if not _steps_fit(self.t_end, self.dt):  # past float's range
            raise _too_many_steps(self.dt)
        positive("solver", "save_dt", self.save_dt, " s")
        if not _steps_fit(self.save_dt, self.dt):  # t_end/dt is a count: save_dt > t_end
            raise ConfigError("solver.save_dt", self.save_dt,
                              f"must be <= t_end = {self.t_end} s")
        if not isinstance(self.method, AbstractIntegrator):
            raise ConfigError("solver.method", self.method, "must be an integrator or its name")
        self.method.validate()
        if (isinstance(self.ledger_every, bool) or not isinstance(self.ledger_every, int)
                or self.ledger_every < 1):
            raise ConfigError("solver.ledger_every", self.ledger_every,
                              "must be an integer >= 1 (steps)")
        if (isinstance(self.event_log, bool) or not isinstance(self.event_log, int)
                or self.event_log < 0):
            raise ConfigError("solver.event_log", self.event_log, "must be an integer >= 0")
        if not isinstance(self.trajectory, bool):
            raise ConfigError("solver.trajectory", self.trajectory, "must be true or false")
        if self.peaks is not None and not all(isinstance(p, str) for p in self.peaks):
            raise ConfigError("solver.peaks", self.peaks, "must be a list of peak names")
        return self

    def validate(self) -> Solver:
        """All settings, and how they relate."""
        self.validate_values()
        if self.t_end < self.dt:
            raise ConfigError("solver.t_end", self.t_end, f"must be >= dt = {self.dt} s "
                              + (f"({self.method.name}'s first step: or give a smaller dt)"
                                 if self.method.dt_is_first_step else "(one step)"))
        if self.save_dt < self.dt:
            raise ConfigError("solver.save_dt", self.save_dt, f"must be >= dt = {self.dt} s")
        if self.save_dt > self.t_end:
            raise ConfigError("solver.save_dt", self.save_dt, f"must be <= t_end = {self.t_end} s")
        if not _whole_steps(self.save_dt, self.dt):
            raise ConfigError("solver.save_dt", self.save_dt,
                              f"must be a whole multiple of dt = {self.dt} s")
        if self.n_saves > SAVES_MAX:
            raise ConfigError("solver.save_dt", self.save_dt,
                              f"gives {self.n_saves} saved samples over t_end = {self.t_end:g} s;"
                              f" at most {SAVES_MAX:.0e}: raise save_dt")
        if self.n_steps > MAX_STEPS:
            raise _too_many_steps(self.dt)
        if self.early_stop or self.ledger_every > 1:
            from ._names import FIXED_STEP_METHODS

            if self.method.name not in FIXED_STEP_METHODS:
                name, val = (("solver.early_stop", True) if self.early_stop else
                             ("solver.ledger_every", self.ledger_every))
                raise ConfigError(name, val, "needs a fixed-step method ("
                                  + ", ".join(FIXED_STEP_METHODS) + ")")
        if self.early_stop:
            if self.n_saves != 1:
                raise ConfigError("solver.early_stop", True, "needs one save interval, the "
                                  f"whole run (save_dt = t_end = {self.t_end} s)")
        return self

    def check_smoothing(self, vehicle) -> Solver:
        """Refuse switch widths too wide to round a switch of ``vehicle`` (a concrete one):
        above ``smoothing_limits``. Wider, the laws are others: a ground rounded over 10 m
        lets the feet sink through it."""
        lim = smoothing_limits(vehicle)
        share = f"{SMOOTHING_SHARE:g} of"
        if self.smoothing_m > lim.length_m:
            raise ConfigError("solver.smoothing_m", self.smoothing_m, f"must be <= "
                              f"{at_most(lim.length_m)} m, {share} the shortest length it "
                              f"rounds on this vehicle ({lim.shortest}, "
                              f"{lim.length_m / SMOOTHING_SHARE * 1e3:.3g} mm); 0: hard "
                              "switches")
        if self.smoothing_N > lim.force_N:
            raise ConfigError("solver.smoothing_N", self.smoothing_N, f"must be <= "
                              f"{at_most(lim.force_N)} N, {share} the honeycomb's plateau "
                              f"force F1 = {lim.force_N / SMOOTHING_SHARE:.4g} N; 0: hard "
                              "switches")
        return self


class SmoothingLimits(NamedTuple):
    length_m: float  # the widest smoothing_m [m]
    force_N: float  # the widest smoothing_N [N]
    shortest: str  # the length that sets length_m


def smoothing_limits(vehicle) -> SmoothingLimits:
    """The widest switch smoothing ``vehicle`` (a concrete one) takes: ``SMOOTHING_SHARE`` of
    the shortest length ``smoothing_m`` rounds (the honeycomb's elastic stroke F1/k_b1; the
    give of the ground and of the strut's top-out stop under one leg's share of the weight)
    and of the plateau force F1 for ``smoothing_N`` (the strut's no-pull floor switches
    between 0 and kilonewtons)."""
    hc, gr, leg = vehicle.honeycomb, vehicle.ground, vehicle.leg
    with np.errstate(all="ignore"):  # a vehicle of 1e308 kg is refused where it overflows
        weight = np.asarray(vehicle.m_quarter + vehicle.m_foot) * np.asarray(vehicle.g)
        lengths = (
            (float(np.min(np.asarray(hc.F1) / np.asarray(hc.k_b1))),
             "the honeycomb's elastic stroke F1/k_b1"),
            (float(np.min(weight / np.asarray(gr.k))),
             "the ground's give under one leg's share of the weight"),
            (float(np.min(weight / np.asarray(leg.k_topout))),
             "the top-out stop's give under one leg's share of the weight"))
    length, shortest = min(lengths)
    return SmoothingLimits(SMOOTHING_SHARE * length,
                           SMOOTHING_SHARE * float(np.min(np.asarray(hc.F1))), shortest)


def check_spec_steps(section: str, dt: float, t_end: float, method: str) -> None:
    """Refuse a spec's run without a trajectory (``[section]`` ``dt_s``, ``t_end_s``,
    ``method``) by its keys: a step that does not divide ``t_end`` into whole steps (the run
    ends on its one save interval, t_end), and what the run's ``Solver`` refuses (its
    duration and step count)."""
    dt_field, t_end_field = f"{section}.dt_s", f"{section}.t_end_s"
    with named_as({"solver.dt": (dt_field, dt), "solver.t_end": (t_end_field, t_end)}):
        # the values and the step count, before the count's fraction
        Solver(dt=dt, t_end=t_end, save_dt=t_end, method=method).validate_values()
    if not _whole_steps(t_end, dt):
        raise ConfigError(dt_field, dt, f"must divide {t_end_field} = {t_end:g} s into whole "
                          f"steps (it gives {t_end / dt:.6g})")
    with named_as({"solver.dt": (dt_field, dt), "solver.t_end": (t_end_field, t_end)}):
        Solver(dt=dt, t_end=t_end, save_dt=t_end, method=method).validate()


def _whole_steps(span: float, dt: float) -> bool:
    """``span`` is a whole number of steps ``dt`` (to 1e-6 of the count: rounding); a count
    past float's range is not."""
    if not _steps_fit(span, dt):
        return False
    ratio = span / dt
    return abs(ratio - round(ratio)) <= 1e-6 * ratio


def _too_many_steps(dt) -> ConfigError:
    return ConfigError("solver.dt", dt, f"t_end/dt must be <= {MAX_STEPS:.0e} steps")


def _steps_fit(span: float, dt: float) -> bool:
    """``span`` [s] is a count of steps ``dt`` [s] within float's range: a Python integer
    can hold it (``round``, ``ceil`` and ``floor`` of an infinite count raise)."""
    return math.isfinite(span / dt)


def _finite_positive(x) -> bool:
    return _is_number(x) and x > 0


# The identity on the outputs of a landing run in a while loop: derivatives forward pass
# through it, and a cotangent reaching it (jax.grad, jax.vjp) is refused by the setting that
# chose the loop, before it reaches the loop, whose own refusal names no setting
_forward_only_p = jax.extend.core.Primitive("jaxland_forward_only")
_forward_only_p.def_impl(lambda x, **_: x)
_forward_only_p.def_abstract_eval(lambda x, **_: x)
ad.primitive_jvps[_forward_only_p] = lambda p, t, **why: (_forward_only_p.bind(p[0], **why),
                                                          _forward_only_p.bind(t[0], **why))
batching.primitive_batchers[_forward_only_p] = lambda x, axes, **why: (
    _forward_only_p.bind(x[0], **why), axes[0])
mlir.register_lowering(_forward_only_p, mlir.lower_fun(lambda x, **_: x,
                                                       multiple_results=False))


def _refuse_cotangent(ct, _, field, value, rule):
    if isinstance(ct, ad.Zero):  # an output the derivative does not use
        return [ct]
    raise ConfigError(field, value, rule)


ad.primitive_transposes[_forward_only_p] = _refuse_cotangent


def forward_only(x, field: str, value, rule: str):
    """``x`` as it is; its reverse-mode derivative is refused as ``ConfigError(field, value,
    rule)`` (the setting that runs the landing in a while loop)."""
    return _forward_only_p.bind(x, field=field, value=value, rule=rule)
