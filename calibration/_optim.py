"""Optimisers for the calibration problem.

* ``levenberg_marquardt``: Gauss-Newton with Marquardt's diagonal damping on the forward-mode
  (``jax.jacfwd``) Jacobian of the weighted residuals, Nielsen's damping update, and a cap on
  each step in the unconstrained coordinates. One Jacobian per accepted step; a rejected step
  costs one forward run. The default: on these problems it converges in ~10-30 iterations.
* ``lbfgs``: ``optax.lbfgs`` with its zoom line search on the scalar loss 0.5 |r|^2, whose
  gradient J^T r is also taken in forward mode (a ``jax.custom_vjp`` hands optax the jacfwd
  gradient, which costs no trajectory memory).

Both report every iteration to ``progress(dict)`` and return ``(theta, history, status)``.
A trial point whose landing fails numerically, or whose residual is not finite, is rejected.
"""

from __future__ import annotations

import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxland as jl

__all__ = ["levenberg_marquardt", "lbfgs"]

MAX_STEP = 0.7  # largest change of any unconstrained coordinate per step (factor 2 in a log)


def levenberg_marquardt(problem, theta0, *, max_iter=60, ftol=1e-10, xtol=1e-9, atol=0.0,
                        progress=None, stage="", t_origin=None, free=None):
    """``free``: a boolean mask of the coordinates that move (default all); the others keep
    their values (their Jacobian columns are computed but not used). Converged when an
    accepted step lowers the loss by less than ``ftol`` of it or by less than ``atol``
    (absolute, in the loss's units, 0.5 chi^2), or moves no coordinate by ``xtol``."""
    theta = np.asarray(theta0, dtype=float).copy()
    free = np.ones(theta.size, bool) if free is None else np.asarray(free, bool)
    r, jac, failed = problem.residuals_and_jacobian(theta)
    if failed or not np.all(np.isfinite(r)):
        raise jl.SimulationError("the landing at the start point failed numerically (non-finite "
                                 "state or energy ledger); check the start values and dt")
    cost = 0.5 * float(r @ r)
    lam, nu = 1e-3, 2.0
    history, status = [], "max_iter"
    t_start = time.perf_counter() if t_origin is None else t_origin
    n_jac, n_fwd = 1, 0
    for it in range(1, max_iter + 1):
        jf = jac[:, free]
        a = jf.T @ jf
        g = jf.T @ r
        d = np.diag(a).copy()
        d = np.maximum(d, 1e-12 * max(float(d.max()), 1e-300))
        scale = np.sqrt(d)
        a_s = a / np.outer(scale, scale)
        g_s = g / scale
        accepted = False
        while True:
            try:
                step_s = -np.linalg.solve(a_s + lam * np.eye(len(g)), g_s)
            except np.linalg.LinAlgError:
                lam *= nu
                nu *= 2.0
                continue
            step = step_s / scale
            big = float(np.max(np.abs(step)))
            if big > MAX_STEP:
                step *= MAX_STEP / big
            trial = theta.copy()
            trial[free] += step
            r_new, failed = problem.residuals(trial)
            n_fwd += 1
            new_cost = 0.5 * float(r_new @ r_new) if np.all(np.isfinite(r_new)) else math.inf
            pred = -(g @ step + 0.5 * step @ a @ step)
            rho = (cost - new_cost) / pred if pred > 0 else -1.0
            if not failed and math.isfinite(new_cost) and new_cost < cost and rho > 1e-4:
                accepted = True
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                break
        if not accepted:
            status = "no_decrease"
            break
        decrease = cost - new_cost
        rel = decrease / max(cost, 1e-300)
        theta = trial
        r, jac, failed = problem.residuals_and_jacobian(theta)
        n_jac += 1
        cost = 0.5 * float(r @ r)
        rec = dict(stage=stage, iteration=it, loss=cost, lambda_=lam,
                   step_max=float(np.max(np.abs(step))), theta=theta.tolist(),
                   values=problem.values(theta).tolist(),
                   wall_s=time.perf_counter() - t_start)
        history.append(rec)
        if progress:
            progress(rec)
        if rel < ftol or decrease < atol or float(np.max(np.abs(step))) < xtol:
            status = "converged"
            break
    return theta, history, dict(status=status, n_jacobians=n_jac, n_forward=n_fwd,
                                final_loss=cost)


def lbfgs(problem, theta0, *, max_iter=200, gtol=1e-8, ftol=1e-12, progress=None, stage="",
          t_origin=None):
    import optax

    res_fn = problem._jac  # (theta, *args) -> (r, J, failed)
    args = problem._args()

    @jax.custom_vjp
    def loss(theta):
        r, _, _ = res_fn(theta, *args)
        return 0.5 * jnp.sum(r * r)

    def loss_fwd(theta):
        r, jac, failed = res_fn(theta, *args)
        val = jnp.where(failed, jnp.inf, 0.5 * jnp.sum(r * r))
        return val, jac.T @ r

    def loss_bwd(grad, ct):
        return (ct * grad,)

    loss.defvjp(loss_fwd, loss_bwd)
    opt = optax.lbfgs()
    value_and_grad = optax.value_and_grad_from_state(loss)

    @jax.jit
    def step(theta, state):
        value, grad = value_and_grad(theta, state=state)
        updates, state = opt.update(grad, state, theta, value=value, grad=grad, value_fn=loss)
        return optax.apply_updates(theta, updates), state, value, grad

    theta = jnp.asarray(theta0, dtype=jnp.float64)
    with jax.numpy_dtype_promotion("standard"):
        state = opt.init(theta)
    # init leaves some counters weakly typed and the step returns them strongly typed: made
    # strong here, the step compiles once per fit instead of twice
    state = jax.tree.map(lambda x: jnp.asarray(x, dtype=x.dtype), state)
    history, status = [], "max_iter"
    t_start = time.perf_counter() if t_origin is None else t_origin
    prev = math.inf
    for it in range(1, max_iter + 1):
        # optax's L-BFGS mixes int32 and int64 counters: allow the standard promotion even
        # where the caller made it strict (as the test suite does)
        with jax.numpy_dtype_promotion("standard"):
            theta, state, value, grad = step(theta, state)
        value = float(value)
        gnorm = float(jnp.max(jnp.abs(grad)))
        rec = dict(stage=stage, iteration=it, loss=value, grad_max=gnorm,
                   theta=np.asarray(theta).tolist(), values=problem.values(theta).tolist(),
                   wall_s=time.perf_counter() - t_start)
        history.append(rec)
        if progress:
            progress(rec)
        if gnorm < gtol * max(1.0, abs(value)) or abs(prev - value) < ftol * max(abs(value),
                                                                                   1e-300):
            status = "converged"
            break
        prev = value
    theta = np.asarray(theta)
    return theta, history, dict(status=status, final_loss=problem.loss(theta))
