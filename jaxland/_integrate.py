"""Integrators: one interface, five methods, every model.

``integrate(model, vehicle, scene, solver)`` runs one landing with ``solver.method``:

``"euler"`` (default)
    Symplectic (semi-implicit) Euler, fixed step, in nested ``lax.scan``. The model evaluates
    its forces at (q_n, v_n), which also advances the constitutive memories (largest crush,
    deepest pit, stick point) by return maps; then v_{n+1} = v_n + dt a, q_{n+1} = q_n +
    dt v_{n+1}. First order; stable while dt^2 w^2 + 2 dt c <= 4 for the stiffest spring w^2 =
    sum k / m2 and the strut damping c = D_b F_bh / m2 on the 1 kg foot (``stable_step``). On
    the paper gear the damping sets the limit (1.3e-4 s, against 4.5e-4 s for the springs).
``"euler_implicit"``
    The same with the strut damping implicit (evaluated at v_{n+1} of the foot, body held;
    ``strut_force``): one evaluation per step, first order, stable to 2/w.
``"verlet"``
    Velocity Verlet (kick-drift-kick), second order where the forces are smooth, the damping on
    a Crank-Nicolson split (implicit first half kick, explicit second): two evaluations per
    step, stable to 2/w.
``"impulse"``
    The paper's discrete-impulse method (sections 2.2, 2.4; quarter model): see
    ``IMPULSE_NOTES``. ``solver.impulse`` is the impulse step dI [N s]; ``solver.dt`` caps the
    time step and is the step in the air.
``"tsit5"``
    diffrax's adaptive Tsit5 with a PIDController (integral gains only, the classic controller)
    on the model's ODE form (quarter model):
    ``solver.rtol``/``atol``; ``solver.max_steps`` bounds the work, and reaching it (a stall at
    a discontinuity) is reported as a failure, as is any other solver failure.

A model is any namespace with ``initial_state``, ``prepare`` (parameter-derived numbers,
computed once before the loop), ``evaluate`` (generalised accelerations at a state, with the
memories advanced; ``kick`` for implicit damping), ``drift`` (positions from the new velocities:
q + dt v, or a rotation update for an attitude), ``energy_scale``, ``apply_scene``,
``accel_record``, ``peak_values``, ``contact_flag``, ``tipping``, ``final_summary``,
``RATE_CHANNELS`` and ``COLUMNS`` (see ``jaxland._quarter`` and ``jaxland._vehicle3d``);
``primary_force`` for ``"impulse"``; ``ode_state``, ``from_ode`` and ``ode_rates`` for
``"tsit5"``.
"""

from __future__ import annotations

import math
import numbers

import equinox as eqx
import jax
import jax.numpy as jnp

from ._errors import ConfigError
from ._params import Vehicle
from ._scene import Scene

N_EVENTS = 256  # capacity of the contact on/off log (later transitions are counted, not stored)
UNROLL = 1  # inner-loop unroll factor (unrolling made the fused step slower on CPU)
ENERGY_TOLERANCE = 0.1  # |ledger residual| above this fraction of the energy scale = failure

METHODS = ("euler", "euler_implicit", "verlet", "impulse", "tsit5")
FIXED_STEP_METHODS = ("euler", "euler_implicit", "verlet")
# shortest time step of the impulse method, as a fraction of its cap solver.dt: a grazing
# contact with a tiny force would otherwise ask for dt = dI / F -> infinity (capped), and a
# force spike for dt -> 0 with time frozen (floored)
IMPULSE_MIN_STEP_FRACTION = 1e-3

IMPULSE_NOTES = """\
The paper's discrete-impulse method, as we read and implement it (quarter model).

In a contact state the impulse of the normal ground spring is the independent variable (paper
Eqs 4-9): each step advances it by dI, so the step lasts dt = dI / F_zs, and every other impulse
(buffer, auxiliary strut, tangential, damping, gravity) is tied to it by its force ratio,
dI_j = (F_j / F_zs) dI = F_j dt. While only the buffer is loaded (state 4) the buffer impulse is
the primary one (paper 2.4); in the air (state 1) time steps, at solver.dt. The state update of
one step is then a symplectic Euler step of length dt, with the same laws and state machine as
the other methods.

Where the paper is ambiguous, and what we chose:
- Spring energy as a state. The paper advances the normal spring's energy E_zs with
  dE_zs/dI_zs = -v_z and takes F_zs = sqrt(2 k E_zs). We take the force from the penetration
  instead (the same in exact arithmetic): a separate energy state drifts away from the foot
  position (seen in a prototype) and cannot carry the pit memory.
- Step bounds. dt = dI / F is infinite at the first touch (F = 0; the integral t ~ sqrt(I) is
  finite) and long wherever the ground force is small, where the stiffer buffer, integrated
  explicitly, would blow up: dt is capped at solver.dt (a stable explicit step). A grazing
  re-contact with the foot's momentum below dI would loop with time frozen: dt is floored at
  IMPULSE_MIN_STEP_FRACTION x the cap.
- Save points. A step is shortened to land on the next save time, so trajectories of every
  method share one time grid.
- The primary force is the total normal force (the spring force times the damping factor
  1 + chi d_dot, which differs from the spring force by < 1e-3 on the paper's gear).
- A stability guard the paper does not have: the step also satisfies dt <= dI / F_bh, the
  honeycomb force (``impulse_step_force``). Near a lift-off the ground force fades while the
  buffer still carries kilonewtons, and dt = dI / F_zs alone would let the strut damping
  D_b F_bh act over a step past its explicit limit. With the guard, c dt <= (D_b + chi) dI / m2
  holds whatever the forces, which is the limit ``stable_step`` states.
"""


class Solver(eqx.Module):
    """Integration settings (static: they set loop lengths and choose code, so they are
    compile-time)."""

    dt: float = eqx.field(static=True, default=1e-5)  # s, step (impulse: cap; tsit5: first)
    t_end: float = eqx.field(static=True, default=1.2)  # s, simulated duration
    save_dt: float = eqx.field(static=True, default=1e-4)  # s, output sample interval
    method: str = eqx.field(static=True, default="euler")  # one of METHODS
    impulse: float = eqx.field(static=True, default=0.05)  # N s, impulse step dI ("impulse")
    rtol: float = eqx.field(static=True, default=1e-6)  # 1, relative tolerance ("tsit5")
    atol: float = eqx.field(static=True, default=1e-9)  # state units, absolute tol. ("tsit5")
    max_steps: int = eqx.field(static=True, default=1_000_000)  # step budget ("tsit5")
    # differentiation of the variable-step methods: "forward" (jax.jacfwd / jvp) or "reverse"
    # (jax.grad); the fixed-step methods take both
    adjoint: str = eqx.field(static=True, default="forward")
    # opt-in smoothing of the force-law switches, for gradient quality in fits (jaxland._laws.
    # _smooth; benchmarks/gradient_quality.py): width of the rounded kinks in length [m] (ground
    # contact, honeycomb unloading, stick/slip, top-out) and in force [N] (the strut's no-pull
    # floor). 0 (default) = the hard switches, bit-identical to the unsmoothed code.
    smoothing_m: float = eqx.field(static=True, default=0.0)
    smoothing_N: float = eqx.field(static=True, default=0.0)

    @property
    def save_every(self) -> int:
        return max(1, int(round(self.save_dt / self.dt)))

    @property
    def n_saves(self) -> int:
        return int(math.ceil(self.t_end / (self.dt * self.save_every)))

    @property
    def n_steps(self) -> int:
        return self.n_saves * self.save_every

    def validate_values(self) -> Solver:
        """Each setting on its own."""
        for name in ("smoothing_m", "smoothing_N"):
            val = getattr(self, name)
            if isinstance(val, bool) or not (
                    isinstance(val, numbers.Real) and math.isfinite(val) and val >= 0):
                raise ConfigError(f"solver.{name}", val,
                                  f"must be a finite number >= 0 {name[-1]}")
        for name in ("dt", "t_end", "save_dt", "impulse", "rtol", "atol"):
            val = getattr(self, name)
            if isinstance(val, bool) or not (
                    isinstance(val, numbers.Real) and math.isfinite(val) and val > 0):
                unit = {"impulse": " N s", "rtol": "", "atol": ""}.get(name, " s")
                raise ConfigError(f"solver.{name}", val, f"must be a finite number > 0{unit}")
        _known_method(self.method)
        if self.adjoint not in ("forward", "reverse"):
            raise ConfigError("solver.adjoint", self.adjoint, "must be 'forward' or 'reverse'")
        if isinstance(self.max_steps, bool) or not isinstance(self.max_steps, int) \
                or self.max_steps < 1:
            raise ConfigError("solver.max_steps", self.max_steps, "must be an integer >= 1")
        return self

    def validate(self) -> Solver:
        """All settings, and how they relate."""
        self.validate_values()
        if self.save_dt < self.dt:
            raise ConfigError("solver.save_dt", self.save_dt, f"must be >= dt = {self.dt} s")
        if self.save_dt > self.t_end:
            raise ConfigError("solver.save_dt", self.save_dt, f"must be <= t_end = {self.t_end} s")
        ratio = self.save_dt / self.dt
        if abs(ratio - round(ratio)) > 1e-6 * ratio:
            raise ConfigError("solver.save_dt", self.save_dt,
                              f"must be a whole multiple of dt = {self.dt} s")
        if self.n_steps > 5e8:
            raise ConfigError("solver.dt", self.dt, "t_end/dt must be <= 5e8 steps")
        return self


def _known_method(method: str) -> None:
    if method not in METHODS:
        raise ConfigError("solver.method", method, f"must be one of {', '.join(METHODS)}")


def check_method(model, method: str) -> None:
    """Refuse a method the model does not provide the hooks for."""
    _known_method(method)
    need = {"impulse": "primary_force", "tsit5": "ode_rates"}.get(method)
    if need is not None and not hasattr(model, need):
        name = model.__name__.rsplit(".", 1)[-1].lstrip("_")
        why = ("four feet each have their own normal impulse, so the paper's single primary "
               "impulse is undefined" if method == "impulse"
               else "its per-foot memories have no ODE form yet")
        raise ConfigError("solver.method", method,
                          f"is available for the quarter model only ({name}: {why}); use one "
                          f"of {', '.join(FIXED_STEP_METHODS)}")


def stable_step(vehicle: Vehicle, *, honeycomb_force=None, normal_force=None,
                bottomed: bool = False, method: str = "euler", impulse=None):
    """Estimated stability limit of the fixed-step methods [s].

    The lightest mass (the foot, m2) is held at once by the stiffest elastic element of the strut
    (k_b1, k_b3, the top-out stop, and k_bottom once the stack has bottomed out), the auxiliary
    struts, the ground in restitution (k / (1 - gamma)) and the tangential spring:
    omega^2 = sum k / m2. The strut damping D_b F_bh and the ground damping chi F_n act on it as a
    viscous coefficient c = (D_b F_bh + chi F_n) / m2; both grow with the force, so the limit
    depends on the landing. For x'' = -omega^2 x - c x' symplectic Euler is stable while
    dt^2 omega^2 + 2 dt c <= 4, i.e. dt <= (sqrt(c^2 + 4 omega^2) - c) / omega^2
    (= 2/omega without damping, 2/c without stiffness). ``"euler_implicit"`` and ``"verlet"``
    take the strut damping implicitly, so only the (small) ground damping remains in c.
    ``"tsit5"`` has no fixed-step limit: inf.

    ``"impulse"`` steps dt = min(dI / F, cap) with explicit forces, and its damping grows with
    the same force F that shortens the step: c dt <= (D_b + chi) dI / m2 whatever F. The worst
    case of dt^2 omega^2 + 2 dt c <= 4 is at F = dI / cap, so the limit on the cap [s] returned
    here is sqrt(4 - 2 dI (D_b + chi) / m2) / omega, for the step ``impulse`` = dI [N s], and
    there is none (0) once dI >= 2 m2 / (D_b + chi): a limit on the impulse step itself,
    independent of the landing.

    Without forces given, the a-priori limit assumes the second plateau F2 for both; after a run,
    pass the peak honeycomb and normal forces it reached (and whether it bottomed out).
    """
    _known_method(method)
    if method == "tsit5":  # adaptive: no fixed-step limit
        return jnp.asarray(jnp.inf)
    hc, leg, gr = vehicle.honeycomb, vehicle.leg, vehicle.ground
    k_el = jnp.maximum(jnp.maximum(hc.k_b1, hc.k_b3), leg.k_topout)
    if bottomed:
        k_el = jnp.maximum(k_el, hc.k_bottom)
    k_sum = k_el + leg.k_a + gr.k / (1.0 - gr.gamma) + gr.k_tan
    m = jnp.minimum(vehicle.m_foot, vehicle.m_quarter)
    f_hc = hc.F2 if honeycomb_force is None else jnp.maximum(hc.F2, honeycomb_force)
    f_n = hc.F2 if normal_force is None else jnp.maximum(hc.F2, normal_force)
    w2 = k_sum / m
    if method == "impulse":
        d_impulse = Solver.impulse if impulse is None else impulse
        room = 4.0 - 2.0 * d_impulse * (leg.D_b + gr.chi) / m
        return jnp.min(jnp.sqrt(jnp.maximum(room, 0.0) / w2))
    strut = 0.0 if method in ("euler_implicit", "verlet") else leg.D_b * f_hc
    c = (strut + gr.chi * f_n) / m
    return jnp.min((jnp.sqrt(c**2 + 4.0 * w2) - c) / w2)


def _setup(model, vehicle: Vehicle, scene: Scene, solver: Solver):
    vehicle = model.apply_scene(vehicle, scene)  # scene-level friction and honeycomb scatter
    derived = model.prepare(vehicle, scene)  # parameter-derived numbers, once, outside the loop
    if solver.smoothing_m or solver.smoothing_N:  # static floats
        derived = dict(derived, smoothing_m=float(solver.smoothing_m),
                       smoothing_N=float(solver.smoothing_N))
    s0 = model.initial_state(vehicle, scene)
    acc0, _, rec0, _, en0 = model.evaluate(vehicle, s0, scene, derived)
    e0 = sum(en0.values()) + jnp.sum(s0.diss_rate)
    return vehicle, derived, s0, e0, model.peak_values(rec0, acc0)


def _track_init(peaks0):
    """Bookkeeping carried alongside the state: running peaks, the contact event log, the
    ledger's worst residual, the failure and tip-over times."""
    return (jax.tree.map(lambda x: jnp.full_like(x, -jnp.inf), peaks0),
            jnp.full((N_EVENTS,), jnp.nan), jnp.zeros((), jnp.int32), jnp.zeros((), bool),
            jnp.zeros(()), -jnp.ones(()), -jnp.ones(()), jnp.zeros((), jnp.int32))


def _track(model, track, s, acc, rec, energy, e0, e_scale):
    """Update the bookkeeping with one evaluated state (full step resolution)."""
    peaks, ev_t, ev_n, prev_c, res_max, fail_t, tip_t, n = track
    residual = sum(energy.values()) + jnp.sum(s.diss_rate) - e0
    # After a tip-over the body (which has no ground contact of its own) is not a landing
    # any more: peaks, the ledger and failure checks stop there; the tip itself counts.
    upright = tip_t < 0.0
    peaks = jax.tree.map(lambda p, x: jnp.where(upright, jnp.maximum(p, x), p), peaks,
                         model.peak_values(rec, acc))
    contact = model.contact_flag(rec)
    touched = (ev_n > 0) | contact  # a foot has been on the ground
    tip_t = jnp.where(upright & touched & model.tipping(rec), s.t, tip_t)
    changed = contact != prev_c
    idx = jnp.minimum(ev_n, N_EVENTS - 1)
    ev_t = ev_t.at[idx].set(jnp.where(changed & (ev_n < N_EVENTS), s.t, ev_t[idx]))
    ev_n = ev_n + changed.astype(ev_n.dtype)
    res_max = jnp.where(upright, jnp.maximum(res_max, jnp.abs(residual)), res_max)
    state_ok = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x))
                                  for x in jax.tree.leaves((s.q, s.v))]))
    bad = ~state_ok | ~(jnp.abs(residual) <= ENERGY_TOLERANCE * e_scale)
    fail_t = jnp.where(bad & upright & (fail_t < 0.0), s.t, fail_t)
    return peaks, ev_t, ev_n, contact, res_max, fail_t, tip_t, n + 1


def _advance(s_m, s, q1, v1, dt, dissipated):
    return eqx.tree_at(lambda x: (x.t, x.q, x.v, x.diss_rate), s_m,
                       (s.t + dt, q1, v1, s.diss_rate + dissipated))


def _kick(v, acc, h):
    return jax.tree.map(lambda x, a: x + h * a, v, acc)


def _step_euler(model, vehicle, s, scene, derived, dt, implicit):
    """Symplectic Euler: forces at (q_n, v_n) (damping at v_{n+1} if ``implicit``), kick, drift.
    Returns the next state and what the bookkeeping reads at this one."""
    acc, s_m, rec, power, energy = model.evaluate(vehicle, s, scene, derived,
                                                  dt if implicit else None)
    v1 = _kick(s.v, acc, dt)
    return _advance(s_m, s, model.drift(s.q, v1, dt), v1, dt, dt * power), (acc, rec, energy)


def _step_verlet(model, vehicle, s, scene, derived, dt):
    """Velocity Verlet (kick-drift-kick), second order, with the strut damping on a
    Crank-Nicolson split: the first half kick takes it implicitly (backward Euler over dt/2),
    the second explicitly from the half-step velocity, so a pure dashpot is damped by
    (1 - a)/(1 + a), a = c dt / 2 m: A-stable, and the stable step is 2/omega of the springs."""
    h = 0.5 * dt
    acc, s_m, rec, p1, energy = model.evaluate(vehicle, s, scene, derived, h)
    v_half = _kick(s.v, acc, h)
    q1 = model.drift(s.q, v_half, dt)
    s_half = eqx.tree_at(lambda x: (x.q, x.v), s_m, (q1, v_half))
    acc2, s_m2, _, p2, _ = model.evaluate(vehicle, s_half, scene, derived)
    v1 = _kick(v_half, acc2, h)
    return _advance(s_m2, s, q1, v1, dt, h * (p1 + p2)), (acc, rec, energy)


def _summary(model, s_end, track, e0, e_scale, vehicle, scene, derived):
    peaks, ev_t, ev_n, _, res_max, fail_t, tip_t, n_steps = track
    _, _, rec_end, _, en_end = model.evaluate(vehicle, s_end, scene, derived)
    dissipated = sum(v for k, v in en_end.items() if k.startswith("diss_"))
    dissipated = dissipated + jnp.sum(s_end.diss_rate)
    return dict(
        **peaks,
        **model.final_summary(s_end, rec_end),
        event_times_s=ev_t,
        n_contact_changes=ev_n,
        energy_initial_J=e0,
        energy_scale_J=e_scale,
        energy_dissipated_J=dissipated,
        energy_closure_max_J=res_max,
        # the ledger error judged by simulate and Monte Carlo: relative to the energy
        # dissipated, or to a tenth of the energy scale when little is dissipated (free fall)
        ledger_error_rel=res_max / jnp.maximum(dissipated, 0.1 * e_scale),
        failed=fail_t >= 0.0,
        failure_time_s=fail_t,
        tipped=tip_t >= 0.0,
        tip_over_time_s=tip_t,
        t_end_s=s_end.t,
        n_steps=n_steps,
        solver_ok=jnp.ones((), bool),
        n_rejected_steps=jnp.zeros((), jnp.int32),
    )


def _save_record(model, vehicle, s, scene, derived, e0, kick=None):
    """The outputs at a saved state, with the forces as the next step applies them (``kick``:
    the implicit-damping kick of the method, ``None`` for explicit). Evaluating the saved state
    here once more is cheaper than taking the block's first step (whose evaluation it repeats)
    out of the inner scan: that restructuring measured 1.3-1.7x slower on XLA:CPU."""
    acc, _, rec, _, energy = model.evaluate(vehicle, s, scene, derived, kick)
    return _record(model, s, acc, rec, energy, e0)


def _record(model, s, acc, rec, energy, e0):
    """The saved outputs at state ``s`` from its evaluation."""
    out = dict(time_s=s.t, **rec, **model.accel_record(acc))
    for i, name in enumerate(model.RATE_CHANNELS):
        out[name] = s.diss_rate[i]
    out["energy_residual_J"] = sum(energy.values()) + jnp.sum(s.diss_rate) - e0
    return out


def integrate(model, vehicle: Vehicle, scene: Scene, solver: Solver):
    """Run one landing. Pure and jittable; vmap over ``scene`` or ``vehicle`` leaves.

    Returns ``(trajectory, summary)``: ``trajectory`` a dict of (n_saves,) arrays named with
    units (sampled every ``solver.save_dt``), ``summary`` a dict of scalars: peaks, memories,
    the contact event log, ledger closure and failure flag, at full step resolution for the
    stepping methods and at the save points for ``tsit5``.
    """
    method = solver.method
    check_method(model, method)
    if method == "tsit5":
        return _integrate_diffrax(model, vehicle, scene, solver)
    vehicle, derived, s0, e0, peaks0 = _setup(model, vehicle, scene, solver)
    e_scale = model.energy_scale(vehicle, scene)

    def tracked(step):
        def body(carry):
            s, track = carry
            s1, (acc, rec, energy) = step(s)
            return s1, _track(model, track, s, acc, rec, energy, e0, e_scale)
        return body

    if method == "impulse":
        inner = _impulse_block(model, vehicle, scene, derived, solver, tracked)
    else:
        if method == "verlet":
            step = lambda s: _step_verlet(model, vehicle, s, scene, derived, solver.dt)  # noqa: E731
        else:
            implicit = method == "euler_implicit"
            step = lambda s: _step_euler(model, vehicle, s, scene, derived, solver.dt,  # noqa: E731
                                         implicit)
        body = tracked(step)

        def inner(carry, i):
            carry, _ = jax.lax.scan(lambda c, _: (body(c), None), carry, None,
                                    length=solver.save_every, unroll=UNROLL)
            return carry

    kick = {"euler_implicit": solver.dt, "verlet": 0.5 * solver.dt}.get(method)

    def save_block(carry, i):
        out = _save_record(model, vehicle, carry[0], scene, derived, e0, kick)
        return inner(carry, i), out

    carry0 = (s0, _track_init(peaks0))
    (s_end, track), traj = jax.lax.scan(save_block, carry0,
                                        jnp.arange(solver.n_saves, dtype=jnp.float64))
    return traj, _summary(model, s_end, track, e0, e_scale, vehicle, scene, derived)


def _impulse_block(model, vehicle, scene, derived, solver, tracked):
    """One save interval of the paper's discrete-impulse method (see ``IMPULSE_NOTES``)."""
    cap, d_impulse = solver.dt, solver.impulse
    dt_floor = cap * IMPULSE_MIN_STEP_FRACTION
    t_save = solver.dt * solver.save_every  # the save interval [s]

    def step_to(target):
        def step(s):
            acc, s_m, rec, power, energy = model.evaluate(vehicle, s, scene, derived)
            f_p = model.impulse_step_force(rec)
            active = f_p > 0.0
            dt = jnp.where(active, d_impulse / jnp.where(active, f_p, 1.0), cap)
            dt = jnp.minimum(jnp.clip(dt, dt_floor, cap), target - s.t)
            v1 = _kick(s.v, acc, dt)
            return _advance(s_m, s, model.drift(s.q, v1, dt), v1, dt, dt * power), \
                (acc, rec, energy)
        return step

    def inner(carry, i):
        target = (i + 1.0) * t_save
        body = tracked(step_to(target))
        # the last step lands on the save time exactly (up to round-off in t)
        cond = lambda c: c[0].t < target - 1e-9 * t_save  # noqa: E731
        kind = "lax" if solver.adjoint == "forward" else "checkpointed"
        max_steps = int(math.ceil(t_save / dt_floor)) + 2
        return eqx.internal.while_loop(cond, body, carry, max_steps=max_steps, kind=kind)

    return inner


def _integrate_diffrax(model, vehicle, scene, solver):
    """Adaptive Runge-Kutta (diffrax Tsit5, PIDController with integral gain only) on the ODE
    form (``ode_rates``: memories in rate form). The first touchdown, found in closed form
    from the free fall, is a jump time of the controller so no step straddles it; later
    contact changes are found by step rejection. Peaks, the event log and the ledger are read
    at the save points."""
    import diffrax

    vehicle, derived, s0, e0, peaks0 = _setup(model, vehicle, scene, solver)
    e_scale = model.energy_scale(vehicle, scene)
    ts = jnp.arange(solver.n_saves, dtype=jnp.float64) * solver.save_dt
    t1 = solver.n_saves * solver.save_dt
    g, v0, h = vehicle.g, scene.sink_speed, scene.drop_height
    t_touch = (jnp.sqrt(v0 * v0 + 2.0 * g * h) - v0) / g
    term = diffrax.ODETerm(lambda t, y, args: model.ode_rates(vehicle, t, y, scene, derived))
    controller = diffrax.ClipStepSizeController(
        diffrax.PIDController(rtol=solver.rtol, atol=solver.atol, pcoeff=0.0, icoeff=1.0,
                              dtmax=solver.save_dt),
        jump_ts=jnp.reshape(t_touch, (1,)))
    adjoint = (diffrax.ForwardMode() if solver.adjoint == "forward"
               else diffrax.RecursiveCheckpointAdjoint())
    sol = diffrax.diffeqsolve(
        term, diffrax.Tsit5(), 0.0, t1, solver.dt, model.ode_state(s0),
        saveat=diffrax.SaveAt(ts=jnp.append(ts, t1)), stepsize_controller=controller,
        max_steps=solver.max_steps, throw=False, adjoint=adjoint)
    ok = sol.result == diffrax.RESULTS.successful
    states = jax.vmap(model.from_ode)(sol.ts, sol.ys)

    def look(track, s):  # one evaluation per saved state, for the bookkeeping and the record
        acc, _, rec, _, energy = model.evaluate(vehicle, s, scene, derived)
        return (_track(model, track, s, acc, rec, energy, e0, e_scale),
                _record(model, s, acc, rec, energy, e0))

    track, traj = jax.lax.scan(look, _track_init(peaks0), states)
    traj = jax.tree.map(lambda x: x[:-1], traj)  # the last state, at t1, is not a save point
    s_end = jax.tree.map(lambda x: x[-1], states)
    summary = _summary(model, s_end, track, e0, e_scale, vehicle, scene, derived)
    # a solver that stopped early leaves the save points it never reached at inf
    reached = jnp.isfinite(sol.ts)
    t_stop = jnp.max(jnp.where(reached, sol.ts, 0.0))
    fail_t = jnp.where(ok, summary["failure_time_s"],
                       jnp.where((summary["failure_time_s"] >= 0.0)
                                 & (summary["failure_time_s"] <= t_stop),
                                 summary["failure_time_s"], t_stop))
    summary.update(failed=fail_t >= 0.0, failure_time_s=fail_t, solver_ok=ok,
                   t_end_s=jnp.where(ok, summary["t_end_s"], t_stop),
                   n_steps=sol.stats["num_accepted_steps"].astype(jnp.int32),
                   n_rejected_steps=sol.stats["num_rejected_steps"].astype(jnp.int32))
    return traj, summary
