"""iLQG with control delay: ``solve`` runs linearise -> backward pass -> line search -> accept/reject
in one compiled ``lax.while_loop``.

One iteration, at the nominal (x_bar, u_bar) with regularisation lambda:

1. linearise (eq. 3-4) and run the backward pass (Theorem 1, or augmentation with
   ``Options(method="augmented")``) with H + lambda I; the structured pass linearises each step
   as it reaches it, so the model is never stored;
2. if some H + lambda I is not positive definite: raise lambda and try again;
3. if the feedforward is negligible (Tassa's gradient measure < tol_grad with lambda < 1e-5): stop;
4. otherwise roll out the delayed feedback law for every alpha in parallel, keep the best (scored
   as the rollouts run, then rolled out again), accept
   when actual / expected reduction > z_min; lower lambda on success, raise it on failure (Tassa's
   schedule); stop when the best reduction is below tol_cost (relative); without noise that last
   step is not taken, and the line search is not run when the model predicts less than that.

The returned policy and ``expected_cost`` come from a backward pass at the returned nominal: the
converging iteration's own, or one more pass when the last iteration moved the nominal.
"""
from __future__ import annotations

from functools import cache, partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _cpu, _precision, _validate
from ..lqg.frame import SlotGains, from_slots
from ..lqg.r_update import DEFER_MIN_LD
from ..options import Options
from ..problem import Problem
from ..solution import Policy, Solution, Status, Trace
from . import implicit, regularization
from .backward import BackwardPass, backward
from .batching import one_after_another
from .line_search import LineSearch, line_search, merit, no_step
from .linearize import rollout, trajectory_cost

__all__ = ["solve", "compiled_solver"]

_RUNNING = -1

# Built once: building and validating an Options costs about as much as a part of a small solve
# (docs/performance.md#_default_options).
_DEFAULT_OPTIONS = Options()


class _State(NamedTuple):
    us: jax.Array
    xs: jax.Array
    cost: jax.Array
    reg: jax.Array
    dreg: jax.Array
    iteration: jax.Array
    status: jax.Array
    final_pass: jax.Array        # bool: the nominal moved after the last backward pass
    gains: SlotGains             # from the last backward pass
    expected_cost: jax.Array     # its J(0)
    trace: Trace


def grad_norm(gains: SlotGains, us):
    """Tassa's gradient measure: mean_k max_i |I_k,i| / (|u_k,i| + 1)."""
    return jnp.mean(jnp.max(jnp.abs(gains.feedforward) / (jnp.abs(us) + 1.0), axis=1))


class _Search(NamedTuple):
    searched: jax.Array          # bool: the line search ran
    flat: jax.Array              # bool: the model predicts too little to search
    model_best: jax.Array        # the model's best reduction over the alphas
    outcome: LineSearch


def _search(problem: Problem, o: Options, bp: BackwardPass, st: _State, merit_now, may_search) -> _Search:
    """The line search, where ``may_search`` and the model predicts enough; else :func:`no_step`.

    Without noise, a model that promises less than tol_cost |cost| for every alpha ends the solve
    before the line search (crocoddyl's stopping test): the step it would find is one the solver
    does not take (``small`` in :func:`_iteration`; docs/performance.md#tol_cost).
    """
    alphas = jnp.asarray(o.alphas)
    model_best = jnp.max(-(alphas * bp.predicted[0] + alphas ** 2 * bp.predicted[1]))
    flat = bp.positive_definite & (model_best >= 0) & (model_best < o.tol_cost * jnp.abs(merit_now)) \
        & (problem.noise is None)
    search = may_search & ~flat
    ls = jax.lax.cond(search, lambda: line_search(problem, bp.gains, bp.S, st.xs, st.us, merit_now, o.alphas, o.z_min,
                                                      bp.predicted),
                      lambda: no_step(st.xs, st.us, st.cost, merit_now))
    return _Search(search, flat, model_best, ls)


def _stop_status(o: Options, converged, small, accept, reg, all_non_finite, pd, it):
    """The stop test: the :class:`Status` the solve ends with after this iteration, or _RUNNING."""
    return jnp.select(
        [converged, small, ~accept & (reg > o.reg_max) & all_non_finite & pd,
         ~accept & (reg > o.reg_max), it >= o.max_iterations],
        [Status.CONVERGED_GRADIENT, Status.CONVERGED_COST, Status.NON_FINITE_ROLLOUT,
         Status.REGULARIZATION_LIMIT, Status.MAX_ITERATIONS], _RUNNING).astype(jnp.int32)


def _record(t: Trace, it, keep, move, s: _Search, converged, merit_now, st: _State, gnorm) -> Trace:
    """The trace with iteration ``it`` written in."""
    ls = s.outcome
    return Trace(
        cost=t.cost.at[it].set(keep(ls.cost, st.cost)),
        merit=t.merit.at[it].set(keep(ls.merit, merit_now)),
        expected_reduction=t.expected_reduction.at[it].set(
            jnp.where(converged, 0.0, jnp.where(s.flat, s.model_best, ls.expected))),
        step_size=t.step_size.at[it].set(jnp.where(move, ls.alpha, 0.0)),
        reg=t.reg.at[it].set(st.reg),
        grad_norm=t.grad_norm.at[it].set(gnorm))


def _iteration(problem: Problem, o: Options, st: _State) -> _State:
    """One pass of the loop: a backward pass at the nominal, then (while running) a line search,
    the regularisation schedule and the stop test.

    When the solve has just stopped with the nominal moved, the loop runs once more for the
    backward pass only, so that the returned policy belongs to the returned nominal. The loop
    body is the only place the backward pass is traced, which keeps compilation short.
    """
    bp = backward(problem, st.xs, st.us, st.reg, o.method, o.limit_margin)
    pd = bp.positive_definite
    running = st.status == _RUNNING
    gnorm = grad_norm(bp.gains, st.us)
    converged = pd & (gnorm < o.tol_grad) & (st.reg < 1e-5)
    # without noise the merit is the cost, already known; with noise S changes it every iteration
    merit_now = st.cost if problem.noise is None else merit(problem, st.xs, st.us, bp.S, st.xs)[1]
    # no line search with the NaN gains of a failed factorisation: lambda is raised instead
    s = _search(problem, o, bp, st, merit_now, running & ~converged & pd)
    ls = s.outcome
    accept = s.searched & ls.accepted
    reg, dreg = regularization.update(st.reg, st.dreg, accept, converged | s.flat, o)
    small = accept & (ls.actual < o.tol_cost * jnp.abs(merit_now))
    # Without noise a step too small to count is not taken: the cost it would remove is below
    # tol_cost |cost|, the nominal keeps the policy of this iteration's backward pass, and the
    # solve needs no further pass for it. With noise the merit is flat along the cost/noise
    # trade-off, and such a step still moves the cost (docs/performance.md#tol_cost): it is taken.
    move = accept & ~small if problem.noise is None else accept
    it = st.iteration + 1
    status = _stop_status(o, converged, s.flat | small, accept, reg, ls.all_non_finite, pd, it)
    keep = lambda new, old: jnp.where(move, new, old)      # a failed step leaves the nominal as it was
    trace = _record(st.trace, it, keep, move, s, converged, merit_now, st, gnorm)
    # one more pass when the stop moved the nominal, or left gains from a failed factorisation
    final_pass = (status != _RUNNING) & (move | ~pd)
    iterated = _State(keep(ls.us, st.us), keep(ls.xs, st.xs), keep(ls.cost, st.cost), reg, dreg, it, status,
                      final_pass, bp.gains, bp.expected_cost, trace)
    finished = st._replace(final_pass=jnp.asarray(False), gains=bp.gains, expected_cost=bp.expected_cost)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(running, a, b), iterated, finished)


def _solve_body(problem: Problem, u_init, options: Options) -> Solution:
    """The solve that is compiled: the rollout of u_init, then :func:`_iteration` until the stop."""
    u_init = jnp.clip(jnp.asarray(u_init, jnp.float64), problem.u_min, problem.u_max)
    xs = rollout(problem, u_init)
    cost = trajectory_cost(problem, xs, u_init)
    ok = jnp.isfinite(cost) & jnp.all(jnp.isfinite(xs))
    nan = jnp.full(options.max_iterations + 1, jnp.nan)
    trace = Trace(cost=nan.at[0].set(cost), merit=nan.at[0].set(cost), expected_reduction=nan,
                  step_size=nan, reg=nan, grad_norm=nan)
    K, nx, nd, l = problem.horizon, problem.n_states, problem.n_controls, problem.delay_steps
    no_gains = SlotGains(jnp.zeros((K, nd)), jnp.zeros((K, nd, nx + l * nd)))
    # a non-finite start stops at once, with one backward pass for the policy it reports
    init = _State(u_init, xs, cost, jnp.asarray(options.reg_init, jnp.float64), jnp.asarray(1.0),
                  jnp.asarray(0, jnp.int32), jnp.where(ok, _RUNNING, Status.NON_FINITE_INITIAL).astype(jnp.int32),
                  ~ok, no_gains, jnp.asarray(jnp.nan), trace)
    st = jax.lax.while_loop(lambda s: (s.status == _RUNNING) | s.final_pass, partial(_iteration, problem, options),
                            init)
    policy = Policy(st.xs, st.us, *from_slots(st.gains, nx))
    return Solution(x=st.xs, u=st.us, cost=st.cost, expected_cost=st.expected_cost, status=st.status,
                    iterations=st.iteration, policy=policy, trace=st.trace)


# Two compilations of one solver. configure_cpu turns YNNPACK's single dots off for the process
# (``_cpu``), so that XLA compiles each scan of a small problem as one function; from
# l d = DEFER_MIN_LD on, where the backward pass defers the R update to large products (and the
# augmented reference's are larger still), those run faster through YNNPACK, and this compilation
# turns it back on (docs/performance.md#_solve_large).
_solve = jax.jit(_solve_body, static_argnames=("options",))
_solve_large = jax.jit(_solve_body, static_argnames=("options",), compiler_options=_cpu.LIBRARY_DOTS)


def compiled_solver(problem: Problem):
    """The jitted ``(problem, u_init, options) -> Solution`` that :func:`solve` calls for ``problem``
    outside JAX transformations."""
    return _solve_large if problem.delay_steps * problem.n_controls >= DEFER_MIN_LD else _solve


@cache
def _one_after_another(options: Options):
    """``_solve`` with ``options`` as a function of (problem, u_init) whose ``vmap`` solves the
    problems one after another (:func:`~delayed_ilqr.ilqg.batching.one_after_another`), the faster
    way on CPU. Elsewhere (GPU) ``solve`` keeps JAX's own batching."""
    return one_after_another(lambda problem, u_init: _solve(problem, u_init, options))


def solve(problem: Problem, u_init=None, options: Options | None = None) -> Solution:
    """Locally-optimal delayed feedback control of ``problem`` by iLQG with input delay.

    Args:
        problem: the :class:`~delayed_ilqr.Problem`.
        u_init: [K, d] initial commands (default zeros, clipped to the limits).
        options: :class:`~delayed_ilqr.Options` (default ``Options()``).

    Returns:
        A :class:`~delayed_ilqr.Solution`. Failures (no descent, blow-up, iteration limit) are
        reported in ``status`` / ``message``, never raised. Works under ``jax.vmap`` over problems
        that differ only in their arrays (x0, cost arrays or parameters, limits); on CPU the
        batch is solved one problem after another in one compiled loop (``_one_after_another``).
    """
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a delayed_ilqr.Problem; got {type(problem).__name__}")
    _precision.require_x64("solve")
    options = _DEFAULT_OPTIONS if options is None else options
    if not isinstance(options, Options):
        raise TypeError(f"options must be a delayed_ilqr.Options; got {type(options).__name__}")
    shape = (problem.horizon, problem.n_controls)
    # set-up outside the compiled solver is numpy only: each eager JAX operation costs tens of
    # microseconds, as much as a whole small solve's backward pass
    if u_init is None:
        u_init = np.zeros(shape)
    elif isinstance(u_init, jax.core.Tracer):
        if u_init.shape != shape:
            raise ValueError(f"u_init must have shape {shape}; got shape {u_init.shape}")
    else:
        u_init = _validate.array(u_init, "u_init", shape, finite=False)
    if not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves((problem, u_init))):
        sol = compiled_solver(problem)(problem, u_init, options)
        return sol._replace(status=Status(int(sol.status)))
    return _differentiable(problem, u_init, options)


def _traced(problem: Problem, u_init, options: Options) -> Solution:
    """The solve inside jit, vmap or differentiation. XLA's options are the outermost compilation's
    (JAX refuses them on a nested jit, so not _solve_large), and on CPU a vmap runs the problems one
    after another."""
    if jax.default_backend() == "cpu":
        return _one_after_another(options)(problem, u_init)
    return _solve(problem, u_init, options)


# derivatives of the traced solve by implicit differentiation at its solution (ilqg/implicit.py)
_differentiable = implicit.differentiable(_traced)
