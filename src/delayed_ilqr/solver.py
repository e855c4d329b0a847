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

import dataclasses
from functools import cache, partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _validate, _xla_options
from .forward import line_search, merit, no_step, predicted_change
from .linearize import linearize, rollout, step_models, trajectory_cost
from .lqg.augmented import augmented_scan
from .lqg.frame import SlotGains, from_slots, to_slots
from .lqg.gains import boxed_gains, unconstrained_gains, unregularized_feedback
from .lqg.r_update import DEFER_MIN_LD as _DEFER_MIN_LD
from .lqg.structured import structured_slot_scan
from .problem import Problem
from .solution import Policy, Solution, Status, Trace

__all__ = ["Options", "solve"]

_RUNNING = -1


@dataclasses.dataclass(frozen=True)
class Options:
    """Solver settings (immutable, validated when built; defaults follow Tassa's iLQG.m where sensible).

    Attributes:
        method: "structured" (Theorem 1, the default) or "augmented" (state-augmentation reference).
        max_iterations: iteration limit (rejected steps count).
        tol_cost: stop when an accepted step would reduce the merit by less than
            tol_cost * |merit| (relative: costs of motor tasks are often ~1e-4, where an absolute
            test stops early). Without noise that last step is not taken, so the returned policy
            is the one of the last backward pass, with no extra pass for the returned nominal; and
            when the backward pass's model predicts less than that for every alpha, the solve
            stops before the line search.
        tol_grad: stop when mean_k max_i |I_k,i| / (|u_k,i| + 1) < tol_grad (and lambda < 1e-5).
        alphas: line-search step sizes, tried in parallel (default 10^linspace(0, -3, 11)).
        reg_init: initial lambda. 0 tries the exact Newton (LQG) step first, which makes a
            linear-quadratic problem converge in one step; Tassa uses 1.
        reg_min, reg_max, reg_factor: Tassa's schedule (lambda below reg_min is set to 0; the
            solve stops when lambda exceeds reg_max).
        z_min: minimal accepted ratio of actual to expected reduction.
        limit_margin: with control limits, commands whose nominal lies at a bound or within
            limit_margin * (u_max - u_min) of one get no feedback (see ``lqg.boxed_gains``).
    """

    method: str = "structured"
    max_iterations: int = 100
    tol_cost: float = 1e-10
    tol_grad: float = 1e-7
    alphas: tuple = tuple(float(a) for a in 10.0 ** np.linspace(0.0, -3.0, 11))
    reg_init: float = 0.0
    reg_min: float = 1e-6
    reg_max: float = 1e10
    reg_factor: float = 1.6
    z_min: float = 0.0
    limit_margin: float = 1e-5

    def __post_init__(self):
        if self.method not in ("structured", "augmented"):
            raise ValueError(f"method must be 'structured' or 'augmented'; got {self.method!r}")
        _validate.positive_int(self.max_iterations, "max_iterations")
        if not (np.isfinite(self.limit_margin) and 0 <= self.limit_margin < 0.5):
            raise ValueError(f"limit_margin must be a number in [0, 0.5); got {self.limit_margin!r}")
        for name in ("tol_cost", "tol_grad", "reg_min", "reg_max"):
            _validate.positive_float(getattr(self, name), name)
        if not (np.isfinite(self.reg_init) and self.reg_init >= 0):
            raise ValueError(f"reg_init must be a finite number >= 0; got {self.reg_init!r}")
        if not float(self.reg_factor) > 1:
            raise ValueError(f"reg_factor must be greater than 1; got {self.reg_factor!r}")
        alphas = tuple(float(a) for a in np.atleast_1d(np.asarray(self.alphas, dtype=float)))
        if not alphas or not all(0 < a <= 1 for a in alphas):
            raise ValueError(f"alphas must be a non-empty sequence of step sizes in (0, 1]; got {self.alphas!r}")
        object.__setattr__(self, "alphas", alphas)


# Built once: building and validating an Options costs about 10 us, 1.5 % of a P1 solve.
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


def _backward(problem: Problem, xs, us, reg, method: str, limit_margin: float):
    """Linearise and solve the LQG: (gains, S [K+1, n, n], s_tilde_0, positive_definite, predicted),
    with predicted the line search's model (a, b). The structured pass linearises each step as it
    reaches it (``linearize.step_models``: the model is never stored) and predicts (a, b) as it
    goes; it returns S = None without noise, where nothing uses it. The augmented reference
    linearises into a stored model and predicts by ``forward.predicted_change``.

    With control limits the feedforward of each step solves a box QP with bounds on du_k
    (u_min - u_k, u_max - u_k), and clamped commands get no feedback. With noise, lambda
    regularises the feedforward only (see ``lqg.unregularized_feedback``).
    """
    kw = dict(gains_fn=unconstrained_gains)
    if problem.has_limits:
        kw = dict(gains_fn=partial(boxed_gains, margin=limit_margin), bounds=(problem.u_min - us, problem.u_max - us))
    if problem.noise is not None:
        kw["gains_fn"] = unregularized_feedback(kw["gains_fn"])
    if method == "augmented":
        lqg = linearize(problem, xs, us)
        gains, value = augmented_scan(lqg, reg, **kw)
        gains = to_slots(gains)
        return gains, value.S, value.s_tilde[0], value.positive_definite, predicted_change(lqg, gains, value.S)
    noisy = problem.noise is not None
    models = step_models(problem, xs, us)
    gains, (s_tilde, *s_and_S), ok, predicted = structured_slot_scan(models, reg, store_value=False, predict=True,
                                                                     store_S=noisy, **kw)
    # S enters the merit and the line search only through the noise terms
    S = jnp.concatenate([s_and_S[1], models.terminal[2][None]]) if noisy else None
    return gains, S, s_tilde[0], ok, predicted


def _grad_norm(gains: SlotGains, us):
    return jnp.mean(jnp.max(jnp.abs(gains.feedforward) / (jnp.abs(us) + 1.0), axis=1))


def _increase(reg, dreg, o: Options):
    dreg = jnp.maximum(dreg * o.reg_factor, o.reg_factor)
    return jnp.maximum(reg * dreg, o.reg_min), dreg


def _decrease(reg, dreg, o: Options):
    dreg = jnp.minimum(dreg / o.reg_factor, 1.0 / o.reg_factor)
    reg = reg * dreg
    return jnp.where(reg > o.reg_min, reg, 0.0), dreg


def _iteration(problem: Problem, o: Options, st: _State) -> _State:
    """One pass of the loop: a backward pass at the nominal, then (while running) a line search.

    When the solve has just stopped with the nominal moved, the loop runs once more for the
    backward pass only, so that the returned policy belongs to the returned nominal. The loop
    body is the only place the backward pass is traced, which keeps compilation short.
    """
    gains, S, expected_cost, pd, predicted = _backward(problem, st.xs, st.us, st.reg, o.method, o.limit_margin)
    running = st.status == _RUNNING
    gnorm = _grad_norm(gains, st.us)
    converged = pd & (gnorm < o.tol_grad) & (st.reg < 1e-5)
    # without noise the merit is the cost, already known; with noise S changes it every iteration
    merit_now = st.cost if problem.noise is None else merit(problem, st.xs, st.us, S, st.xs)[1]
    # Without noise, a model that promises less than tol_cost |cost| for every alpha ends the
    # solve before the line search (crocoddyl's stopping test): the step it would find is one the
    # solver does not take (``small`` below). P3: one line search of nine fewer.
    alphas = jnp.asarray(o.alphas)
    model_best = jnp.max(-(alphas * predicted[0] + alphas ** 2 * predicted[1]))
    flat = pd & (model_best >= 0) & (model_best < o.tol_cost * jnp.abs(merit_now)) & (problem.noise is None)
    # no line search with the NaN gains of a failed factorisation: lambda is raised instead
    search = running & ~converged & pd & ~flat
    ls = jax.lax.cond(search, lambda: line_search(problem, gains, S, st.xs, st.us, merit_now, o.alphas, o.z_min,
                                                      predicted),
                      lambda: no_step(st.xs, st.us, st.cost, merit_now))
    accept = search & ls.accepted
    reg_up, dreg_up = _increase(st.reg, st.dreg, o)
    reg_down, dreg_down = _decrease(st.reg, st.dreg, o)
    reg = jnp.where(accept, reg_down, jnp.where(converged | flat, st.reg, reg_up))
    dreg = jnp.where(accept, dreg_down, jnp.where(converged | flat, st.dreg, dreg_up))
    small = accept & (ls.actual < o.tol_cost * jnp.abs(merit_now))
    # Without noise a step too small to count is not taken: the cost it would remove is below
    # tol_cost |cost|, the nominal keeps the policy of this iteration's backward pass, and the
    # solve needs no further pass for it (P3: 10 -> 9 passes). With noise the merit is flat along
    # the cost/noise trade-off, and such a step still moved the cost by 3.4e-6 (relative) on
    # P2-noisy: it is taken.
    move = accept & ~small if problem.noise is None else accept
    it = st.iteration + 1
    status = jnp.select(
        [converged, flat | small, ~accept & (reg > o.reg_max) & ls.all_non_finite & pd,
         ~accept & (reg > o.reg_max), it >= o.max_iterations],
        [Status.CONVERGED_GRADIENT, Status.CONVERGED_COST, Status.NON_FINITE_ROLLOUT,
         Status.REGULARIZATION_LIMIT, Status.MAX_ITERATIONS], _RUNNING).astype(jnp.int32)
    keep = lambda new, old: jnp.where(move, new, old)      # a failed step leaves the nominal as it was
    t = st.trace
    trace = Trace(
        cost=t.cost.at[it].set(keep(ls.cost, st.cost)),
        merit=t.merit.at[it].set(keep(ls.merit, merit_now)),
        expected_reduction=t.expected_reduction.at[it].set(
            jnp.where(converged, 0.0, jnp.where(flat, model_best, ls.expected))),
        step_size=t.step_size.at[it].set(jnp.where(move, ls.alpha, 0.0)),
        reg=t.reg.at[it].set(st.reg),
        grad_norm=t.grad_norm.at[it].set(gnorm))
    # one more pass when the stop moved the nominal, or left gains from a failed factorisation
    final_pass = (status != _RUNNING) & (move | ~pd)
    iterated = _State(keep(ls.us, st.us), keep(ls.xs, st.xs), keep(ls.cost, st.cost), reg, dreg, it, status,
                      final_pass, gains, expected_cost, trace)
    finished = st._replace(final_pass=jnp.asarray(False), gains=gains, expected_cost=expected_cost)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(running, a, b), iterated, finished)


def _solve_body(problem: Problem, u_init, options: Options) -> Solution:
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


# Two compilations of one solver. The package turns YNNPACK's single dots off for the process
# (``_xla_options``), so that XLA compiles each scan of a small problem as one function; from
# l d = _DEFER_MIN_LD on, where the backward pass defers the R update to large products (and the
# augmented reference's are larger still), those run faster through YNNPACK (P4 at l = 200: 77-85
# ms with it, 91-97 ms without), and this compilation turns it back on.
_solve = jax.jit(_solve_body, static_argnames=("options",))
_solve_large = jax.jit(_solve_body, static_argnames=("options",), compiler_options=_xla_options.LIBRARY_DOTS)


def compiled_solver(problem: Problem):
    """The jitted ``(problem, u_init, options) -> Solution`` that :func:`solve` calls for ``problem``
    outside JAX transformations."""
    return _solve_large if problem.delay_steps * problem.n_controls >= _DEFER_MIN_LD else _solve


@cache
def _one_after_another(options: Options):
    """``_solve`` with ``options`` as a function of (problem, u_init) whose ``vmap`` solves the
    problems one after another in one compiled loop (``lax.map``), not all at once.

    On CPU that is faster: each problem's scans stay small enough to be compiled as one function
    (see ``_xla_options``), where a batched step does B times their work through separate
    operations, and each problem stops when it converges, where a batched ``while_loop`` runs every
    problem until the last one stops (and its line search at every iteration). 64 P2 targets in one
    ``jax.jit(jax.vmap(solve))`` call: 0.88-0.93 ms per problem, against 1.8-2.0 ms batched step by
    step and 1.0-1.3 ms for separate solves (separate processes, alternately). Elsewhere (GPU)
    ``solve`` keeps JAX's own batching.
    """
    @jax.custom_batching.custom_vmap
    def run(problem, u_init):
        return _solve(problem, u_init, options)

    @run.def_vmap
    def batched(axis_size, in_batched, problem, u_init):
        args = jax.tree_util.tree_map(lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)),
                                      (problem, u_init), tuple(in_batched))
        out = jax.lax.map(lambda a: run(*a), args)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return run


def solve(problem: Problem, u_init=None, options: Options | None = None) -> Solution:
    """Locally-optimal delayed feedback control of ``problem`` by iLQG with input delay.

    Args:
        problem: the :class:`~delayed_ilqr.Problem`.
        u_init: [K, d] initial commands (default zeros, clipped to the limits).
        options: :class:`Options` (default ``Options()``).

    Returns:
        A :class:`~delayed_ilqr.Solution`. Failures (no descent, blow-up, iteration limit) are
        reported in ``status`` / ``message``, never raised. Works under ``jax.vmap`` over problems
        that differ only in their arrays (x0, cost arrays or parameters, limits); on CPU the
        batch is solved one problem after another in one compiled loop (``_one_after_another``).
    """
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a delayed_ilqr.Problem; got {type(problem).__name__}")
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
        return compiled_solver(problem)(problem, u_init, options)
    # inside jit or vmap: XLA's options are the outermost compilation's (JAX refuses them on a
    # nested jit, so not _solve_large), and on CPU a vmap runs the problems one after another
    if jax.default_backend() == "cpu":
        return _one_after_another(options)(problem, u_init)
    return _solve(problem, u_init, options)
