"""Gradient-based landing-gear design, robust over a fixed set of dispersed touchdowns.

The problem (docs/design.md; the spec format in docs/formats.md)::

    minimise    J(x) = R_obj[a_peak(x, s)] / a0  +  w_m * m_gear(x) / m0
    subject to  g_i(x) = R_i[b_i(x, s)] / scale_i <= 0,       x in [low, high]

* ``x`` are the design variables (``VARIABLES``): plateau forces F1, F2, or the cell size and
  foil thickness of each stage through Wierzbicki's crush formula (something one can buy), the
  stage lengths x_L2 and x_L4, the auxiliary strut stiffness k_a, the strut angle theta_b and
  the joint radius R. Each is mapped from an unconstrained ``z`` by a smooth transform,
  ``x = low + (high - low) sigmoid(z)`` (or the same in log x): bounds hold exactly and are
  never enforced by clipping. Orderings the honeycomb law needs (F2 > F1, x_L4 > x_L3) are
  built into the transform: the lower bound of F2 (x_L4) moves with F1 (x_L2).
* ``s`` are ``n_scenes`` scenes drawn once from the Monte Carlo dispersion with ``scene_seed``
  (``jaxland._montecarlo.sample_scenes``); they stay fixed through the optimisation (sample
  average approximation), so the robust objective is a deterministic function of ``x``.
* ``R`` is a risk measure over those scenes: ``mean``, ``cvar`` at ``level`` (the mean of the
  worst (1 - level) fraction, with the fractional sample weighted), ``max``, or ``normal`` at
  ``level``: mean + z_level std, the level-quantile of a normal fitted to the scenes. ``max``
  and ``cvar`` of N scenes cannot see beyond the N-th worst outcome (a fresh landing exceeds
  the max of N with probability 1/(N + 1)); ``normal`` extrapolates to quantiles the scenes do
  not reach, and every scene carries gradient (no switching of the worst scene).
* ``a_peak`` is the peak body acceleration of each landing as the integrator keeps it: the
  running maximum at every step. Its gradient is the slope at the step where the maximum
  occurs, which is the derivative of the maximum wherever that step is unique (Danskin). We
  measured a smooth maximum (log-sum-exp over the saved trace) and did not use it: see
  ``benchmarks/bench_design.py`` for its bias. So no smoothing enters, and the verification
  Monte Carlo judges the same quantities the optimiser saw.
* The constraints' per-scene "badness" ``b_i`` (positive = violated):
  ``stroke``: max stroke (any leg) - (x_L4 - margin), no bottoming out with a margin;
  ``stability``: threshold - minimum stability margin over the landing (full 3-D model);
  ``slip``: foot slip distance (any leg) - limit.
* ``m_gear`` is a documented mass proxy (``gear_mass_kg``).

Method: the augmented Lagrangian of Powell-Hestenes-Rockafellar for inequalities,

    L(z; lam, rho) = J + sum_i (rho / 2) [max(0, g_i + lam_i / rho)^2 - (lam_i / rho)^2],

minimised in ``z`` by optax: ``clip_by_global_norm(clip_norm)`` then ``scale_by_adam``, with
the step from an optax schedule (``lr_schedule``: cosine or exponential decay to
``lr_final`` x ``learning_rate``, or constant). The clip matters: one step across a stroke
constraint returns a penalty gradient ~100x the objective's, and Adam's second moment would
remember it for ~100 iterations (b2 = 0.9), shrinking every later step (measured in
``benchmarks/bench_design.py``). Every ``outer_every`` iterations the multipliers are updated,
``lam_i <- max(0, lam_i + rho g_i)``,
and ``rho`` grows by ``penalty_growth`` when the worst violation did not at least halve. The
gradients of J and every g_i come from one forward-mode Jacobian (``jax.jacfwd`` through the
vmapped batch of landings, no trajectory memory), and L's gradient is assembled from them on the
host, so changing multipliers never recompiles.

The returned design is the best iterate that satisfies every constraint to ``feasibility_tol``
(in the normalised units of g). If no iterate does, the result's ``status`` is
``"infeasible"`` and ``violated`` names each violated constraint with its value.
"""

from ._gear import apply_design as apply_design, gear_mass_kg as gear_mass_kg
from ._optimise import (
    DesignResult as DesignResult,
    optimise_design as optimise_design,
    step_schedule as step_schedule,
)
from ._problem import (
    DesignProblem as DesignProblem,
    check_bounds as check_bounds,
    risk_measure as risk_measure,
)
from ._spec import (
    CONSTRAINTS as CONSTRAINTS,
    VARIABLES as VARIABLES,
    Constraint as Constraint,
    DesignSpec as DesignSpec,
    DesignVariable as DesignVariable,
    Objective as Objective,
    design_spec_from_dict as design_spec_from_dict,
    load_design_spec as load_design_spec,
)
from ._verify import (
    check_verification as check_verification,
    design_verified as design_verified,
    verify_design as verify_design,
)
