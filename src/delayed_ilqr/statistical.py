"""Feedback gains re-designed by statistical linearisation (SL) around the closed loop's predicted
distribution (``docs/results/noise_calibration.md`` §5.5).

The solver's gains are those of the LQG linearised at the nominal (x_bar, u_bar) (eq. 3). When the
closed loop's trials leave the range of that linearisation (the six-muscle arm with 50-100 ms of
delay), the LQG's model is wrong where the trials are. SL keeps the nominal and replaces the
LQG's dynamics matrices by their expectations under the closed loop's own distribution, then
re-solves for the gains, to a fixed point. With the policy's gains G = (I, L, M) and its closed
loop's Markov state z_k = [dx_k; du_{k-l}; ...; du_{k-1}] (N = n + l d entries; deviations from the
nominal, the pending commands' those of the clipped commands sent, oldest first), each
iteration:

1. (mean_k [N], P_k [N, N]) = ``prediction.closed_loop_prediction(problem, G, rule).z``, the moments
   of z_k under the Gaussian closure (eq. P1-P4 there);
2. the expected Jacobians of the Euler step x' = x + dt f(x, u, ud) over z_k ~ N(mean_k, P_k), by
   sigma points Z_i, weights w_i (the rule's, in the r = n + 2d inputs of the plant's step,
   ``prediction`` eq. P5; fifth-degree points for ``"second_order"``, whose expansion of a
   Jacobian would need the plant's third derivatives):

       x_i = x_bar_k + dx_i,  u_i = clip(u_bar_k + [L_k M_k] Z_i),  ud_i = u_bar_{k-l} + du_{k-l,i}
       A_k = sum_i w_i (I + dt f_x(x_i, u_i, ud_i)),   B0_k = sum_i w_i dt f_u(.),
       B1_k = sum_i w_i dt f_ud(.)                                                         (SL1)

   (ud_i = u_i at l = 0); the noise terms (c, C0, C1) and the cost terms stay those of the
   nominal's linearisation (``ilqg.linearize.linearize``);
3. G_new = the gains of that LQG by the solver's backward pass and gain rule: Theorem 1's
   structured scan with ``lqg.gains.boxed_gains`` (margin ``Options.limit_margin``, bounds
   u_min - u_bar_k, u_max - u_bar_k, the solver's feedback latch held) for a plant with limits,
   ``unconstrained_gains`` without, wrapped in ``unregularized_feedback`` with noise; lambda = 0;
4. G <- relax G_new + (1 - relax) G (I, L and M alike); the relative change of the feedback
   ||[L M]_new - [L M]|| / ||[L M]|| (Frobenius over all steps) says whether G is a fixed point.
                                                                                           (SL2)

The solver's feedback latch (commands held without feedback, ``docs/derivation.md`` §12) is not
part of a Solution: [`solver_latch`][delayed_ilqr.statistical.solver_latch] recovers it as the commands that the pass on the nominal's
own LQG gives feedback and the solver's policy does not, grown to a fixed point (holding one
command frees others upstream). On a linear plant SL1 is the nominal's A, B0, B1 whatever the
distribution, and SL returns the solver's gains.

Not done: the nominal and feedforward are not re-optimised with the SL model, the noise and cost
terms are not averaged, and nothing guarantees a fixed point: read ``change``.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

from . import _delays
from .lqg.law import augmented_feedback
from .ilqg.linearize import delayed_commands, linearize
from .lqg import Gains, policy_cost
from .lqg.frame import from_slots
from .lqg.gains import boxed_gains, unconstrained_gains, unregularized_feedback
from .lqg.structured import structured_slot_scan
from .options import Options
from .prediction import _closed_loop_prediction, _check_closure_input, _inputs_map, _sigma_points, acting_command
from .problem import Problem
from .solution import Policy

__all__ = ["StatisticalFeedback", "statistical_feedback", "expected_jacobians", "solver_latch"]


class StatisticalFeedback(NamedTuple):
    """The result of [`statistical_feedback`][delayed_ilqr.statistical.statistical_feedback].

    Attributes:
        policy: the input policy with the SL gains: the same nominal (x_nominal [K+1, n],
            u_nominal [K, d]); feedforward [K, d] I_k, state_feedback [K, d, n] L_k and
            delay_feedback [K, l, d, d] M_k those of the last relaxed iteration (SL2).
        change: [] the last iteration's relative feedback change (SL2); near 0 at a fixed point.
        changes: [iterations] the change of each iteration.
        predicted_cost: [] E[J] of ``policy`` on the plant by the Gaussian closure
            (``closed_loop_prediction``, same rule).
        model_cost: [] the exact expected cost of ``policy``'s gains (feedforward 0) on the SL
            model's LQG at ``policy`` (``lqg.policy_cost``).
        predicted_costs: [iterations] ``predicted_cost`` of the gains each iteration started from.
        model_costs: [iterations] ``model_cost`` of the gains each iteration started from.
        latch: [K, d] bool, the solver's feedback latch held in every pass ([`solver_latch`][delayed_ilqr.statistical.solver_latch]).
        latch_error: [] relative difference between the input policy's feedback and the pass's
            on the nominal's LQG with that latch: round-off when the latch is recovered.
    """

    policy: Policy
    change: jax.Array
    changes: jax.Array
    predicted_cost: jax.Array
    model_cost: jax.Array
    predicted_costs: jax.Array
    model_costs: jax.Array
    latch: jax.Array
    latch_error: jax.Array


def _gains(policy: Policy) -> Gains:
    return Gains(policy.feedforward, policy.state_feedback, policy.delay_feedback)


def expected_jacobians(problem: Problem, policy: Policy, z_mean, z_cov, rule: str):
    """Eq. SL1: A [K, n, n], B0 [K, n, d], B1 [K, n, d], each step's Jacobians of the Euler step
    averaged over the points of ``rule`` for z_k ~ N(z_mean_k, z_cov_k) (z_mean [K+1, N], z_cov
    [K+1, N, N]),
    at the points' actual states and clipped commands, as ``closed_loop_prediction`` runs them.
    ``problem`` without a frame, or with per-channel delays in the frame L of its longest;
    ``policy`` of delay l (N = n + l d; per channel, of the frame: N = n + L d)."""
    nx, nd, l, dt = problem.n_states, problem.n_controls, problem.delay_steps, problem.dt
    m = problem.frame_steps if _delays.is_per_channel(l) else l
    points_rule = "fifth_degree" if rule == "second_order" else rule
    eye = jnp.eye(nx, dtype=z_mean.dtype)

    def at_point(z, x_bar, u_bar, u_bar_delayed, LMk, t):
        x = x_bar + z[:nx]
        u = jnp.clip(u_bar + LMk @ z, problem.u_min, problem.u_max)
        ud = acting_command(u, u_bar_delayed, z[nx:].reshape(m, nd), l)
        fx, fu, fud = jax.jacrev(lambda *a: problem.dynamics_at(*a, t), argnums=(0, 1, 2))(x, u, ud)
        return eye + dt * fx, dt * fu, dt * fud

    def step(row):
        mean, cov, x_bar, u_bar, u_bar_delayed, LMk, t = row
        Z, w, _ = _sigma_points(mean, cov, points_rule, _inputs_map(nx, nd, l, m, m, LMk))
        A, B0, B1 = jax.vmap(at_point, in_axes=(0,) + (None,) * 5)(Z, x_bar, u_bar, u_bar_delayed, LMk, t)
        return tuple(jnp.tensordot(w, J, axes=1) for J in (A, B0, B1))

    rows = (z_mean[:-1], z_cov[:-1], policy.x_nominal[:-1], policy.u_nominal,
            delayed_commands(problem, policy.u_nominal), augmented_feedback(_gains(policy)),
            problem.step_times(z_mean.dtype))
    return jax.lax.map(step, rows)


def _backward_gains(problem: Problem, lqg, u_bar, limit_margin, held) -> Gains:
    """SL2's step 3: the gains of ``lqg`` by the solver's structured pass and gain rule
    (``ilqg.backward.backward`` with lambda = 0 and the feedback latch ``held`` [K, d] bool)."""
    gains_fn, bounds = unconstrained_gains, None
    if problem.has_limits:
        gains_fn = partial(boxed_gains, margin=limit_margin)
        bounds = (problem.u_min - u_bar, problem.u_max - u_bar, held)
    if problem.noise is not None:
        gains_fn = unregularized_feedback(gains_fn)
    slots, _, _ = structured_slot_scan(lqg, 0.0, store_value=False, gains_fn=gains_fn, bounds=bounds, store_S=False)
    return from_slots(slots, problem.n_states)


def _feedback_rows(gains: Gains):
    """[K, d] bool: the commands with a nonzero feedback row."""
    return jnp.any(augmented_feedback(gains) != 0, axis=-1)


def _relative_change(new: Gains, old: Gains):
    F_old, F_new = augmented_feedback(old), augmented_feedback(new)
    return jnp.linalg.norm(F_new - F_old) / jnp.linalg.norm(F_old)


def solver_latch(problem: Problem, policy: Policy, limit_margin):
    """The solver's feedback latch, which a Solution does not return, recovered: (held [K, d] bool,
    the relative difference between ``policy``'s feedback and the backward pass's on the nominal's
    own LQG with that latch). held grows from none by the commands without feedback in the policy
    that the pass with the latch so far gives feedback, until none is left; the difference is then
    round-off unless the solver's last pass was regularised where H is not positive definite.
    Without limits nothing is held. ``problem`` without a frame."""
    nominal = linearize(problem, policy.x_nominal, policy.u_nominal)
    without = ~_feedback_rows(_gains(policy))
    pass_with = lambda held: _backward_gains(problem, nominal, policy.u_nominal, limit_margin, held)

    def grow(state):
        held, _ = state
        more = held | (_feedback_rows(pass_with(held)) & without)
        return more, jnp.any(more != held)

    none = jnp.zeros_like(without)
    held = jax.lax.while_loop(lambda state: state[1], grow, (none, jnp.asarray(problem.has_limits)))[0]
    return held, _relative_change(pass_with(held), _gains(policy))


@partial(jax.jit, static_argnames=("rule", "iterations"))
def _statistical_feedback(problem: Problem, policy: Policy, limit_margin, relax, rule: str,
                          iterations: int) -> StatisticalFeedback:
    nominal = linearize(problem, policy.x_nominal, policy.u_nominal)
    held, latch_error = solver_latch(problem, policy, limit_margin)

    def model_of(current: Policy):
        """The SL model's LQG at ``current`` (SL1) and the closure's E[J] of ``current``."""
        closure = _closed_loop_prediction(problem, current, rule)
        A, B0, B1 = expected_jacobians(problem, current, closure.z.mean, closure.z.cov, rule)
        return nominal.replace(A=A, B0=B0, B1=B1), closure.expected_cost

    def model_cost(model, gains: Gains):
        return policy_cost(model, gains._replace(feedforward=jnp.zeros_like(gains.feedforward)))

    def iteration(current: Policy, _):
        """SL2 once: the relaxed policy; (change, model cost, closure cost) of the gains it started from."""
        model, predicted = model_of(current)
        old = _gains(current)
        new = _backward_gains(problem, model, policy.u_nominal, limit_margin, held)
        relaxed = jax.tree_util.tree_map(lambda a, b: relax * a + (1 - relax) * b, new, old)
        return current._replace(**relaxed._asdict()), (_relative_change(new, old), model_cost(model, old), predicted)

    final, (changes, model_costs, predicted_costs) = jax.lax.scan(iteration, policy, None, length=iterations)
    model, predicted = model_of(final)
    return StatisticalFeedback(final, changes[-1], changes, predicted, model_cost(model, _gains(final)),
                               predicted_costs, model_costs, held, latch_error)


def statistical_feedback(problem: Problem, policy: Policy, options: Optional[Options] = None, *,
                         rule: str = "fifth_degree", iterations: int = 8, relax: float = 0.5) -> StatisticalFeedback:
    """``policy``'s feedback gains re-designed by statistical linearisation around its closed loop's
    predicted distribution (module docstring, eq. SL1-SL2), from ``policy`` itself.

    Use it for a noise-aware design whose trials leave the nominal's linear range (the six-muscle
    arm with 50-100 ms of delay: ``docs/results/noise_calibration.md`` §5.5); on a nearly linear
    plant it changes little. The nominal and feedforward are not moved, the noise and cost terms
    stay the nominal's, and a fixed point is not guaranteed: check ``change``.

    Args:
        problem: the plant the policy was designed for, full-state feedback (no observation); a
            problem with a ``delay_frame`` is taken without it (its delay must be static).
        policy: a [`Policy`][delayed_ilqr.Policy] without estimator, of the plant's delay, e.g.
            ``solve(problem).policy``.
        options: the solver's [`Options`][delayed_ilqr.Options] (its ``limit_margin``); default
            ``Options()``.
        rule: the closure's rule, one of ``prediction.RULES``.
        iterations: number of SL2 iterations (>= 1; static: one compilation per value).
        relax: the relaxation of SL2 step 4, in (0, 1].

    Returns:
        [`StatisticalFeedback`][delayed_ilqr.statistical.StatisticalFeedback]: the policy with SL gains, the last and every change, the
        closure's and the SL model's expected cost, the latch held. One compiled function: a
        ``lax.scan`` over iterations; per iteration one closure and one Jacobian pass over the
        rule's points (O(K r^2) plant Jacobians for fifth degree, r = n + 2d) and one backward pass.

    Raises:
        ValueError: float64 off, a problem with an observation or a policy with an estimator, a
            policy whose delay is not the plant's, an unknown rule, iterations < 1, relax outside
            (0, 1].
    """
    _check_closure_input("statistical.statistical_feedback", problem, policy, rule)
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"statistical_feedback: iterations must be an integer >= 1; got {iterations!r}")
    if not 0.0 < float(relax) <= 1.0:
        raise ValueError(f"statistical_feedback: relax must be in (0, 1]; got {relax!r}")
    options = Options() if options is None else options
    frame = problem.delay_frame
    if _delays.is_per_channel(problem.delay_steps):
        problem = problem.replace(delay_frame=None)          # the frame of the longest channel delay, as solve's
        if problem.delay_frame != policy.delay_feedback.shape[1]:
            raise ValueError(f"statistical_feedback: policy.delay_feedback has {policy.delay_feedback.shape[1]} "
                             f"delay steps, the problem's longest channel delay is {problem.delay_frame}; SL "
                             "re-designs the gains for the plant's own delays")
        return _statistical_feedback(problem, policy, options.limit_margin, relax, rule, iterations)
    problem = problem.without_frame("statistical_feedback")
    l, l_p = problem.delay_steps, policy.delay_feedback.shape[1]
    if frame is not None and l_p == frame and frame != l:
        # a framed solve's untrimmed feedback: its first L - l entries act on commands already applied
        policy = policy._replace(delay_feedback=policy.delay_feedback[:, frame - l:])
    elif l_p != l:
        raise ValueError(f"statistical_feedback: policy.delay_feedback has {l_p} delay steps, the problem's delay "
                         f"is {l}; SL re-designs the gains for the plant's own delay")
    return _statistical_feedback(problem, policy, options.limit_margin, relax, rule, iterations)
