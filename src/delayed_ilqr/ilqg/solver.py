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
   schedule); stop when the best reduction is below tol_cost (relative) and `first_order`
   certifies the nominal (lambda < 1e-5 and the Newton step's promise below tol_cost; met under a
   larger lambda, the next pass runs at lambda = 0 to confirm it); without noise that last
   step is not taken, and the line search is not run when the model predicts less than that.

With noise and limits, commands whose feedback keeps switching on and off while the merit stalls
in a cycle lose their feedback for good (the latch, `LATCH_STALL`); with noise, a stop without
convergence returns the nominal of lowest merit seen (derivation §12).

No returned policy holds NaN: when the backward pass at the final nominal gives non-finite gains,
the last nominal whose gains were finite is returned with them (``Status.NON_FINITE_GAINS``). Under
``jit`` or ``vmap`` the rules a concrete [`Problem`][delayed_ilqr.Problem] is checked against when it
is built (a non-empty command box, a framed delay within its frame) are checked in the compiled
solve instead, which does not run when one is broken (``Status.INVALID_TRACED_INPUT``).

The returned policy and ``expected_cost`` come from a backward pass at the returned nominal: the
converging iteration's own, or one more pass when the last iteration moved the nominal. For a
problem with delayed sensors (``Problem.observation``) the controller is that of the same problem
without them (one compiled solver for both), and the delayed Kalman filter of the linearisation
at the returned nominal is added after it (``estimation.with_estimator``; with signal-dependent
noise, Todorov's alternation then redesigns the filter and the feedback), with ``expected_cost``
the exact cost of the controller on its estimate.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _cpu, _delays, _precision, _validate
from ..lqg.frame import SlotGains, from_slots
from ..lqg.r_update import DEFER_MIN_LD
from ..options import Options, replaced
from ..problem import Problem
from ..solution import Policy, Solution, Status, Trace
from . import implicit, regularization
from .backward import BackwardPass, backward
from .batching import one_after_another
from .jittered import solve_jittered
from .estimation import all_finite as _all_finite, with_estimator, without_observation
from .line_search import LineSearch, line_search, merit, no_step
from .linearize import rollout, trajectory_cost

__all__ = ["solve", "compiled_solver"]

_RUNNING = -1

# Built once: building and validating an Options costs about as much as a part of a small solve
# (docs/performance.md#_default_options).
_DEFAULT_OPTIONS = Options()


class _Latch(NamedTuple):
    """The noisy solver's feedback latch (with noise and limits only; derivation §12)."""

    feedback: jax.Array          # [K, d] bool: the command got feedback in the last backward pass
    toggles: jax.Array           # [K, d] int32: how often that has switched since the best merit improved
    stall: jax.Array             # int32: iterations since the best merit improved
    held: jax.Array              # [K, d] bool: no feedback from now on
    low: jax.Array               # the lowest and highest merit (each nominal's under its own S)
    high: jax.Array              # since the count began
    last: jax.Array              # [2]: (low, high) of the window before (NaN: none)


class _Best(NamedTuple):
    """The nominal of lowest merit (under its own S) seen so far (with noise only)."""

    us: jax.Array
    xs: jax.Array
    cost: jax.Array
    merit: jax.Array


class _Finite(NamedTuple):
    """The last nominal whose backward pass gave finite gains, with them: what the solve returns
    when the pass at its final nominal does not (``Status.NON_FINITE_GAINS``)."""

    us: jax.Array
    xs: jax.Array
    cost: jax.Array
    gains: SlotGains
    expected_cost: jax.Array


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
    latch: _Latch | None         # None without noise or without limits
    best: _Best | None           # None without noise
    finite: _Finite


def grad_norm(gains: SlotGains, us):
    """Tassa's gradient measure: mean_k max_i |I_k,i| / (|u_k,i| + 1)."""
    return jnp.mean(jnp.max(jnp.abs(gains.feedforward) / (jnp.abs(us) + 1.0), axis=1))


# Below this lambda the regularised step is taken for the (projected) Newton step of the LQG
# model: the gradient test and the cost tests count as convergence only there (Tassa's 1e-5).
NEWTON_REG = 1e-5

#: The relative change of the merit that round-off lets a line search resolve (about 1000 eps: the
#: merit sums K running costs). When Options.tol_cost asks for less and the Newton step promises
#: less than this, no cost comparison can certify or refute a step: the solver takes the full
#: Newton step without a line search, and only the gradient test ends the solve (derivation §12).
ROUNDOFF = 1e3 * float(np.finfo(np.float64).eps)

#: With noise and limits, when the best merit has not improved for LATCH_STALL iterations, every
#: command whose feedback has been switched on and off again (at least LATCH_TOGGLES switches
#: between successive backward passes) in that time gets no feedback for the rest of the solve:
#: the latch that turns the noisy iteration's cycles into a fixed point (derivation §12).
LATCH_STALL = 10
LATCH_TOGGLES = 2

#: ... and only when the iteration recurs: the lowest and the highest merit (each nominal's under
#: its own S) of those LATCH_STALL iterations are within LATCH_RECUR (relative) of those of the
#: LATCH_STALL iterations before. A cycle of the feedback pattern (period up to LATCH_STALL)
#: revisits the same nominals window after window; an iteration still on its way, whose feedback
#: pattern changes because the nominal moves, does not, and latching there fixes an arbitrary
#: pattern (derivation §12).
LATCH_RECUR = 1e-2


def first_order(o: Options, bp: BackwardPass, reg, merit_now):
    """The first-order certificate every convergence status requires.

    With lambda < NEWTON_REG the feedforward is the (box-projected) Newton step of the LQG model,
    and its full step (alpha = 1) promises the merit reduction -(a + b) = g' H^-1 g / 2 (the
    squared Newton decrement over two, projected with the limits): the model's first-order
    optimality measure. The certificate is: H + lambda I positive definite, lambda < NEWTON_REG
    and that promise below tol_cost |merit|. A large lambda or tiny step sizes make every promise
    small, so neither can end a solve as converged.
    """
    return bp.positive_definite & (reg < NEWTON_REG) & (newton_promise(bp) < o.tol_cost * jnp.abs(merit_now))


def newton_promise(bp: BackwardPass):
    """-(a + b): the merit reduction the LQG model promises for the full step (alpha = 1)."""
    return -(bp.predicted[0] + bp.predicted[1])


def _feedback_mask(gains: SlotGains):
    """[K, d] bool: the commands whose feedback row (L_k and every M_k^i) is not zero."""
    return jnp.any(gains.feedback != 0, axis=-1)


def _latched(latch: _Latch, gains: SlotGains, counts, improved, merit_now) -> _Latch:
    """The latch after a backward pass with ``gains`` (its switches counted where ``counts``), at a
    nominal of merit ``merit_now`` (NaN: not known) that ``improved`` the best merit or not."""
    feedback = _feedback_mask(gains)
    toggles = latch.toggles + (counts & (feedback != latch.feedback)).astype(jnp.int32)
    stall = latch.stall + 1
    low, high = jnp.fmin(latch.low, merit_now), jnp.fmax(latch.high, merit_now)
    fire = stall >= LATCH_STALL
    recurs = jnp.all(jnp.abs(jnp.stack([low, high]) - latch.last) <= LATCH_RECUR * jnp.abs(latch.last))
    held = latch.held | (fire & recurs & (toggles >= LATCH_TOGGLES))
    reset = improved | fire
    last = jnp.where(improved, jnp.nan, jnp.where(fire, jnp.stack([low, high]), latch.last))
    return _Latch(jnp.where(counts, feedback, latch.feedback), jnp.where(reset, 0, toggles),
                  jnp.where(reset, 0, stall), held, jnp.where(reset, jnp.inf, low), jnp.where(reset, -jnp.inf, high),
                  last)


class _Search(NamedTuple):
    searched: jax.Array          # bool: the line search ran
    flat: jax.Array              # bool: the model predicts too little to search (and is certified)
    promise_small: jax.Array     # bool: it predicts too little, certified or not
    model_best: jax.Array        # the model's best reduction over the alphas
    outcome: LineSearch


def _search(problem: Problem, o: Options, bp: BackwardPass, st: _State, merit_now, may_search,
            certified, beyond_roundoff) -> _Search:
    """The line search, where ``may_search`` and the model predicts enough; else `no_step`.

    Without noise, a model that promises less than tol_cost |cost| for every alpha ends the solve
    before the line search (crocoddyl's stopping test) when `first_order` certifies it: the
    step it would find is one the solver does not take (``small`` in `_iteration`;
    docs/performance.md#tol_cost).
    """
    alphas = jnp.asarray(o.alphas)
    model_best = jnp.max(-(alphas * bp.predicted[0] + alphas ** 2 * bp.predicted[1]))
    promise_small = bp.positive_definite & (model_best >= 0) & (model_best < o.tol_cost * jnp.abs(merit_now)) \
        & (problem.noise is None)
    flat = promise_small & certified
    search = may_search & ~flat
    # beyond round-off every candidate is the full Newton step, accepted if its rollout is finite
    alphas = jnp.where(beyond_roundoff, 1.0, alphas)
    z_min = jnp.where(beyond_roundoff, -jnp.inf, o.z_min)
    ls = jax.lax.cond(search, lambda: line_search(problem, bp.gains, bp.S, st.xs, st.us, merit_now, alphas, z_min,
                                                      bp.predicted),
                      lambda: no_step(st.xs, st.us, st.cost, merit_now))
    return _Search(search, flat, promise_small, model_best, ls)


def _stop_status(o: Options, converged, small, accept, reg, all_non_finite, pd, it):
    """The stop test: the [`Status`][delayed_ilqr.Status] the solve ends with after this iteration, or _RUNNING."""
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
    held = None if st.latch is None else st.latch.held
    bp = backward(problem, st.xs, st.us, st.reg, o.method, o.limit_margin, held)
    pd = bp.positive_definite
    usable = pd & _all_finite(bp.gains) & jnp.isfinite(bp.expected_cost)
    finite = jax.tree_util.tree_map(lambda a, b: jnp.where(usable, a, b),
                                    _Finite(st.us, st.xs, st.cost, bp.gains, bp.expected_cost), st.finite)
    running = st.status == _RUNNING
    gnorm = grad_norm(bp.gains, st.us)
    converged = pd & (gnorm < o.tol_grad) & (st.reg < NEWTON_REG)
    # without noise the merit is the cost, already known; with noise S changes it every iteration
    merit_now = st.cost if problem.noise is None else merit(problem, st.xs, st.us, bp.S, st.xs)[1]
    certified = first_order(o, bp, st.reg, merit_now)
    beyond_roundoff = pd & (st.reg < NEWTON_REG) & (o.tol_cost < ROUNDOFF) \
        & (newton_promise(bp) < ROUNDOFF * jnp.abs(merit_now))
    # no line search with the NaN gains of a failed factorisation: lambda is raised instead
    s = _search(problem, o, bp, st, merit_now, running & ~converged & pd, certified, beyond_roundoff)
    ls = s.outcome
    accept = s.searched & ls.accepted
    reg, dreg = regularization.update(st.reg, st.dreg, accept, converged | s.flat, o)
    small_step = accept & (ls.actual < o.tol_cost * jnp.abs(merit_now))
    small = small_step & certified & ~beyond_roundoff
    # a cost test met under a large lambda (a shortened gradient step, not a Newton step) is
    # confirmed or refuted by the next pass at lambda = 0
    confirm = (s.promise_small | small_step) & (st.reg >= NEWTON_REG)
    reg, dreg = jnp.where(confirm, 0.0, reg), jnp.where(confirm, 1.0, dreg)
    # Without noise a step too small to count is not taken: the cost it would remove is below
    # tol_cost |cost|, the nominal keeps the policy of this iteration's backward pass, and the
    # solve needs no further pass for it. With noise the merit is flat along the cost/noise
    # trade-off, and such a step still moves the cost (docs/performance.md#tol_cost): it is taken.
    move = accept & ~small if problem.noise is None else accept
    it = st.iteration + 1
    status = _stop_status(o, converged, s.flat | small, accept, reg, ls.all_non_finite, pd, it)
    keep = lambda new, old: jnp.where(move, new, old)      # a failed step leaves the nominal as it was
    trace = _record(st.trace, it, keep, move, s, converged, merit_now, st, gnorm)
    us, xs, cost = keep(ls.us, st.us), keep(ls.xs, st.xs), keep(ls.cost, st.cost)
    best, restore, improved = st.best, jnp.asarray(False), None
    if best is not None:
        # With noise the merit of successive nominals is each under its own S, and an iteration
        # that does not converge may end above a nominal it passed: a stop without convergence
        # returns the best nominal whose merit is known (this one's, or an earlier one's).
        better = pd & (merit_now < best.merit)
        improved = pd & (merit_now < best.merit - o.tol_cost * jnp.abs(best.merit))
        best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), _Best(st.us, st.xs, st.cost, merit_now),
                                      best)
        failed = (status != _RUNNING) & ~((status == Status.CONVERGED_GRADIENT) | (status == Status.CONVERGED_COST))
        us, xs, cost = (jnp.where(failed, a, b) for a, b in ((best.us, us), (best.xs, xs), (best.cost, cost)))
        restore = failed & ~better
        move = move & ~failed
    latch = st.latch if st.latch is None else _latched(st.latch, bp.gains, pd & (st.iteration > 0), improved,
                                                       jnp.where(pd, merit_now, jnp.nan))
    # one more pass when the stop moved the nominal, or left gains from a failed factorisation
    final_pass = (status != _RUNNING) & (move | ~pd | restore)
    iterated = _State(us, xs, cost, reg, dreg, it, status, final_pass, bp.gains, bp.expected_cost, trace, latch,
                      best, finite)
    finished = st._replace(final_pass=jnp.asarray(False), gains=bp.gains, expected_cost=bp.expected_cost,
                           finite=finite)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(running, a, b), iterated, finished)


def broken_traced_rules(problem: Problem):
    """Whether a traced field of ``problem`` breaks a rule that [`Problem`][delayed_ilqr.Problem]
    checks when it is concrete (then this is a constant False): limits with u_min >= u_max (or
    NaN) in some component, a framed delay outside 0..min(L, K - 1). The solve then does not run
    (``Status.INVALID_TRACED_INPUT``)."""
    broken = jnp.asarray(False)
    if problem.has_limits:
        broken = broken | ~jnp.all(problem.u_min < problem.u_max)
    if problem.delay_frame is not None:
        l = problem.delay_steps
        broken = broken | jnp.any((l < 0) | (l > problem.delay_frame) | (l >= problem.horizon))   # l_j per channel
    return broken


def _solve_body(problem: Problem, u_init, options: Options) -> Solution:
    """The solve that is compiled: the rollout of u_init, then `_iteration` until the stop."""
    invalid = broken_traced_rules(problem)
    u_init = jnp.asarray(u_init, jnp.float64)
    # (limits that break the rules would make the clipped commands NaN)
    u_init = jnp.where(invalid, u_init, jnp.clip(u_init, problem.u_min, problem.u_max))
    xs = rollout(problem, u_init)
    cost = trajectory_cost(problem, xs, u_init)
    ok = jnp.isfinite(cost) & jnp.all(jnp.isfinite(xs))
    nan = jnp.full(options.max_iterations + 1, jnp.nan)
    trace = Trace(cost=nan.at[0].set(cost), merit=nan.at[0].set(cost), expected_reduction=nan,
                  step_size=nan, reg=nan, grad_norm=nan)
    K, nx, nd, l = problem.horizon, problem.n_states, problem.n_controls, problem.frame_steps
    no_gains = SlotGains(jnp.zeros((K, nd)), jnp.zeros((K, nd, nx + l * nd)))
    # a non-finite start stops at once, with one backward pass for the policy it reports
    noisy = problem.noise is not None
    latch = _Latch(jnp.zeros((K, nd), bool), jnp.zeros((K, nd), jnp.int32), jnp.asarray(0, jnp.int32),
                   jnp.zeros((K, nd), bool), jnp.asarray(jnp.inf), jnp.asarray(-jnp.inf),
                   jnp.full(2, jnp.nan)) \
        if noisy and problem.has_limits else None
    best = _Best(u_init, xs, cost, jnp.asarray(jnp.inf)) if noisy else None
    status = jnp.where(invalid, Status.INVALID_TRACED_INPUT, jnp.where(ok, _RUNNING, Status.NON_FINITE_INITIAL))
    init = _State(u_init, xs, cost, jnp.asarray(options.reg_init, jnp.float64), jnp.asarray(1.0),
                  jnp.asarray(0, jnp.int32), status.astype(jnp.int32), ~ok & ~invalid, no_gains,
                  jnp.asarray(jnp.nan), trace, latch, best,
                  _Finite(u_init, xs, cost, no_gains, jnp.asarray(jnp.nan)))
    st = jax.lax.while_loop(lambda s: (s.status == _RUNNING) | s.final_pass, partial(_iteration, problem, options),
                            init)
    # no NaN in a returned policy: when the pass at the final nominal failed, the last nominal
    # with finite gains is returned, with them (u_init's rollout and no feedback if none had)
    failed = ~(_all_finite(st.gains) & jnp.isfinite(st.expected_cost))
    last = _Finite(st.us, st.xs, st.cost, st.gains, st.expected_cost)
    last = jax.tree_util.tree_map(lambda a, b: jnp.where(failed, a, b), st.finite, last)
    status = jnp.where(failed & (st.status != Status.NON_FINITE_INITIAL) & ~invalid, Status.NON_FINITE_GAINS,
                       st.status).astype(jnp.int32)
    policy = Policy(last.xs, last.us, *from_slots(last.gains, nx))
    return Solution(x=last.xs, u=last.us, cost=last.cost, expected_cost=last.expected_cost, status=status,
                    iterations=st.iteration, policy=policy, trace=st.trace)


# Two compilations of one solver. configure_cpu turns YNNPACK's single dots off for the process
# (``_cpu``), so that XLA compiles each scan of a small problem as one function; from
# l d = DEFER_MIN_LD on, where the backward pass defers the R update to large products (and the
# augmented reference's are larger still), those run faster through YNNPACK, and this compilation
# turns it back on (docs/performance.md#_solve_large). The options are a pytree argument: their
# numbers are traced, their structure is static (``options.STRUCTURE``), so options that differ
# only in their numbers share the compilation.
_solve = jax.jit(_solve_body)
_solve_large = jax.jit(_solve_body, compiler_options=_cpu.LIBRARY_DOTS)


def compiled_solver(problem: Problem):
    """The jitted ``(problem, u_init, options) -> Solution`` that [`solve`][delayed_ilqr.solve] calls for ``problem``
    outside JAX transformations: the large products' compilation from L d = ``DEFER_MIN_LD`` pending
    components on (L the frame, or the delay without one), where the backward pass defers its blocks."""
    return _solve_large if problem.frame_steps * problem.n_controls >= DEFER_MIN_LD else _solve


#: ``_solve`` whose ``vmap`` solves the problems one after another (`one_after_another`), the
#: faster way on CPU. Elsewhere (GPU) ``solve`` keeps JAX's own batching.
_one_after_another = one_after_another(_solve)


def solve(problem: Problem, u_init=None, options: Options | None = None) -> Solution:
    """Locally-optimal delayed feedback control of ``problem`` by iLQG with input delay.

    Args:
        problem: the [`Problem`][delayed_ilqr.Problem].
        u_init: [K, d] initial commands (default zeros, clipped to the limits).
        options: [`Options`][delayed_ilqr.Options] (default ``Options()``).

    Returns:
        A [`Solution`][delayed_ilqr.Solution]. Failures (no descent, blow-up, iteration limit) are
        reported in ``status`` / ``message``, never raised; a converged status is certified
        first-order (``first_order``), and a noisy solve that does not converge returns the
        nominal of lowest merit it met, with that nominal's policy (derivation §12). Works under ``jax.vmap`` over problems
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
    if problem.observation is not None:
        # the controller is designed with the full state; the filter is added to its solution
        # (max_alternations does not change that solve: the default's compiled solver serves all)
        full_state = replaced(options, max_alternations=_DEFAULT_OPTIONS.max_alternations)
        return with_estimator(problem, solve(without_observation(problem), u_init, full_state), options)
    if problem.delay_jitter is not None:     # the delay drawn at every step (derivation §21)
        sol = solve_jittered(problem, u_init, options)
        return sol if isinstance(sol.status, jax.core.Tracer) else sol._replace(status=Status(int(sol.status)))
    if not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves((problem, u_init, options))):
        sol = compiled_solver(problem)(problem, u_init, options)
        return _trimmed(problem, sol._replace(status=Status(int(sol.status))))
    return _differentiable(problem, u_init, options)


def _trimmed(problem: Problem, sol: Solution) -> Solution:
    """With a frame and a known delay l, the policy's delay feedback cut to its l live entries (the
    frame's first L - l, on commands that have acted, are zero): the policy of the unframed solve."""
    if problem.delay_frame is None:
        return sol
    L, l = problem.delay_frame, _delays.longest(problem.delay_steps)
    return sol._replace(policy=sol.policy._replace(delay_feedback=sol.policy.delay_feedback[:, L - l:]))


def _traced(problem: Problem, u_init, options: Options) -> Solution:
    """The solve inside jit, vmap or differentiation. XLA's options are the outermost compilation's
    (JAX refuses them on a nested jit, so not _solve_large), and on CPU a vmap runs the problems one
    after another."""
    if jax.default_backend() == "cpu":
        return _one_after_another(problem, u_init, options)
    return _solve(problem, u_init, options)


# derivatives of the traced solve by implicit differentiation at its solution (ilqg/implicit.py)
_differentiable = implicit.differentiable(_traced)
