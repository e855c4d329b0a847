"""What a solution predicts about its own trials: the mean and covariance of the states, and of the
task-space point (the arms' hand), from the exact second moments of the linearised closed loop.

The policy runs on the plant as [`delayed_ilqr.simulate`][delayed_ilqr.simulate] runs it (eq. 6 without the
feedforward). Linearised at the nominal (eq. 3, the solver's model), the deviations
z_k = [dx_k, du_{k-l}, ..., du_{k-1}] of that closed loop start at 0, have mean 0 and the second
moments of [`delayed_ilqr.lqg.closed_loop_moments`][delayed_ilqr.lqg.closed_loop_moments] (signal-dependent noise included). So, to
first order in the noise:

    E[x_k] = x_nominal_k,   Cov(x_k) = E[dx_k dx_k']
    E[e_k] = e(x_nominal_k),   Cov(e_k) = J_k Cov(x_k) J_k'     (e the task map, J_k = de/dx at x_nominal_k)

Everything is differentiable: through [`delayed_ilqr.solve`][delayed_ilqr.solve] (``docs/derivation.md`` §16) these
are the model's predictions as functions of its parameters, which is what fitting a model to
measured reaches needs (``delayed_ilqr.experiments.fitting``). The prediction ignores what the
linearisation leaves out: the clipping of commands at their limits, and the plant's curvature
(``docs/fitting.md`` measures the gap against Monte Carlo).

[`closed_loop_prediction`][delayed_ilqr.prediction.closed_loop_prediction] takes the plant's curvature in: it propagates the mean and
covariance of the nonlinear closed loop (state and pending commands) under a Gaussian closure, by
a second-order expansion or by sigma points, and returns its expected cost (eq. P1-P4 there).
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _delays, _precision
from .lqg.law import augmented_feedback
from .ilqg.linearize import linearize
from .lqg import Gains
from .lqg.exact import closed_loop_moments
from .lqg.frame import acting_commands
from .models.metadata import task_space
from .problem import Problem
from .solution import Policy, Solution

__all__ = ["Prediction", "predict", "task_prediction", "ClosedLoopPrediction", "closed_loop_prediction", "RULES"]


class Prediction(NamedTuple):
    """Predicted mean and covariance of a quantity along the trials.

    Attributes:
        mean: [K+1, m] E[y_k].
        cov: [K+1, m, m] Cov(y_k).
    """

    mean: jax.Array
    cov: jax.Array


def predict(problem: Problem, solution: Solution) -> Prediction:
    """The states' mean [K+1, n] and covariance [K+1, n, n] under ``solution.policy`` on ``problem``
    (module docstring). Full-state feedback only: a policy with an estimator raises ``ValueError``."""
    if problem.observation is not None or solution.policy.estimator is not None:
        raise ValueError("predict: problem.observation must be None (full-state feedback); got a policy with "
                         "an estimator, whose closed loop this function does not model")
    policy = solution.policy
    if problem.delay_frame is not None and policy.delay_feedback.shape[1] != problem.delay_frame:
        if problem.is_fractional:       # its frame stays: the trimmed entries (commands that have acted) are zero
            M = policy.delay_feedback
            pad = jnp.zeros((M.shape[0], problem.delay_frame - M.shape[1]) + M.shape[2:], M.dtype)
            policy = policy._replace(delay_feedback=jnp.concatenate([pad, M], axis=1))
        else:
            problem = problem.without_frame("predict")       # a policy trimmed by solve
    gains = Gains(jnp.zeros_like(policy.feedforward), policy.state_feedback, policy.delay_feedback)
    moments = closed_loop_moments(linearize(problem, solution.x, solution.u), gains)
    return Prediction(solution.x, moments.state_covariance(problem.n_states))


def task_prediction(problem: Problem, states: Prediction) -> Prediction:
    """The task-space point's mean [K+1, m] and covariance [K+1, m, m] (first order through the
    model's task map, ``ModelMetadata.task``); ``ValueError`` for a problem without a task space."""
    task = task_space(problem)
    if task is None:
        raise ValueError(f"task_prediction: problem {problem.name!r} has no task space (metadata.task is None)")
    J = jax.vmap(jax.jacobian(task.map))(states.mean)                   # [K+1, m, n]
    return Prediction(task.map(states.mean), J @ states.cov @ jnp.swapaxes(J, 1, 2))


RULES = ("second_order", "fifth_degree", "cubature")
"""The expectation rules of [`closed_loop_prediction`][delayed_ilqr.prediction.closed_loop_prediction] (eq. P3-P4)."""


class ClosedLoopPrediction(NamedTuple):
    """Moments of the nonlinear closed loop from [`closed_loop_prediction`][delayed_ilqr.prediction.closed_loop_prediction].

    Attributes:
        expected_cost: [] E[J], eq. (2) of the trials as [`delayed_ilqr.simulate`][delayed_ilqr.simulate] scores them.
        state: [`Prediction`][delayed_ilqr.prediction.Prediction] of the states: mean [K+1, n] E[x_k], cov [K+1, n, n] Cov(x_k).
        z: [`Prediction`][delayed_ilqr.prediction.Prediction] of the whole Markov state of eq. P1, z_k = [dx_k; du_{k-m}; ...;
            du_{k-1}] (deviations from the nominal; the pending commands' deviations are those of
            the clipped commands sent, oldest first): mean [K+1, N] E[z_k], cov [K+1, N, N]
            Cov(z_k), N = n + m d. Its first n entries are ``state`` less the nominal; the rest is
            what a model of the closed loop around its actual distribution (rather than the
            nominal) needs, e.g. expected Jacobians.
    """

    expected_cost: jax.Array
    state: Prediction
    z: Prediction


def _inputs_map(nx: int, nd: int, l, l_p: int, m: int, LMk):
    """T_k [r, N] of eq. P5: y = T_k z = [dx_k; L_k dx_k + sum_i M_k^i du_{k+i-l_p}; du_{k-l}] (the
    last block only for l > 0; with per-channel delays l [d], component j of du_{k-l_j}), the
    arguments of everything nonlinear in eq. P1 (the plant, the clip, the noise and the running
    cost); z_k of N = nx + m nd entries, ``LMk`` [nd, nx + l_p nd]."""
    N = nx + m * nd
    feedback = jnp.zeros((nd, N), LMk.dtype).at[:, :nx].set(LMk[:, :nx]).at[:, nx + (m - l_p) * nd:].set(LMk[:, nx:])
    rows = [jnp.eye(nx, N, dtype=LMk.dtype), feedback]
    if _delays.is_per_channel(l) and m > 0:
        j = jnp.arange(nd)
        rows.append(jnp.zeros((nd, N), LMk.dtype).at[j, nx + jnp.clip(m - l, 0, m - 1) * nd + j].set(1.0))
    elif not _delays.is_per_channel(l) and l > 0:
        rows.append(jnp.eye(nd, N, nx + (m - l) * nd, dtype=LMk.dtype))
    return jnp.concatenate(rows)


def acting_command(u, ud_bar, sent, l):
    """The command acting at a point of the chain, u_{k-l} = ud_bar + du_{k-l} (u itself where the
    delay is 0): ``sent`` [m, d] the pending deviations du_{k-m}..du_{k-1}; with per-channel delays
    l [d] (traced), component j of du_{k-l_j}."""
    m, nd = sent.shape
    if not _delays.is_per_channel(l):
        return ud_bar + sent[m - l] if l > 0 else u
    if m == 0:
        return u
    return jnp.where(l == 0, u, ud_bar + sent[jnp.clip(m - l, 0, m - 1), jnp.arange(nd)])


def _rule_root(cov, inputs):
    """(R [N, r], E [N, N]) with R R' + E = cov and inputs E = 0 (eq. P5): R spans what ``inputs``
    [r, N] sees of z ~ N(., cov), E is the rest. cov PSD and possibly singular (the pending commands
    before time 0): its square root S is the symmetric one, from ``eigh``. ``inputs`` None, or with
    r >= N rows: R = S, E = 0 (the rule runs in all N dimensions)."""
    values, vectors = jnp.linalg.eigh(0.5 * (cov + cov.T))
    root = vectors * jnp.sqrt(jnp.maximum(values, 0.0))[None, :]      # root root' = cov
    N = cov.shape[0]
    if inputs is None or inputs.shape[0] >= N:
        return root, jnp.zeros_like(cov)
    # inputs S = U s W' (thin SVD, W [N, r] orthonormal): y - mean_y = U s W' xi, xi ~ N(0, I_N); the
    # part of S xi that y sees is S W (W' xi), and S (I - W W') xi is independent of y
    W = jnp.linalg.svd(inputs @ root, full_matrices=False)[2].T
    seen = root @ W
    rest = root - seen @ W.T
    return seen, rest @ rest.T


def _unit_rule(r: int, rule: str):
    """The unit points [P, r] and weights [P] (sum 1) of ``rule`` for N(0, I_r) (eq. P4); numpy, r
    static."""
    eye = np.eye(r)
    if rule == "cubature":
        return np.sqrt(r) * np.concatenate([eye, -eye]), np.full(2 * r, 1.0 / (2 * r))
    i, j = np.triu_indices(r, 1)
    pairs = np.concatenate([eye[i] + eye[j], eye[i] - eye[j], -eye[i] + eye[j], -eye[i] - eye[j]])
    unit = np.concatenate([np.zeros((1, r)), np.sqrt(r + 2.0) * eye, -np.sqrt(r + 2.0) * eye,
                           np.sqrt((r + 2.0) / 2) * pairs])
    weights = np.concatenate([[2.0 / (r + 2)], np.full(2 * r, (4.0 - r) / (2 * (r + 2) ** 2)),
                              np.full(len(pairs), 1.0 / (r + 2) ** 2)])
    return unit, weights


def _sigma_points(mean, cov, rule: str, inputs=None):
    """Points Z [P, N] and weights w [P] (sum 1) of ``rule`` for the functions of y = inputs z,
    z ~ N(mean [N], cov [N, N]), and the covariance E [N, N] of the part of z they leave out (eq.
    P5): the rule runs in r = min(rows of inputs, N) dimensions."""
    root, rest = _rule_root(cov, inputs)
    unit, weights = _unit_rule(root.shape[1], rule)
    return mean + jnp.asarray(unit, mean.dtype) @ root.T, jnp.asarray(weights, mean.dtype), rest


@partial(jax.jit, static_argnames=("rule",))
def _closed_loop_prediction(problem: Problem, policy: Policy, rule: str) -> ClosedLoopPrediction:
    K, nx, nd = problem.horizon, problem.n_states, problem.n_controls
    l, l_p = problem.delay_steps, policy.delay_feedback.shape[1]
    per_channel = _delays.is_per_channel(l)       # l [d], traced: the frame of L slots is static
    m = max(problem.frame_steps if per_channel else l, l_p)
    dtype = problem.x0.dtype
    LM = augmented_feedback(Gains(policy.feedforward, policy.state_feedback, policy.delay_feedback))
    u_bar = policy.u_nominal
    # u_nominal_{k-l} (zero before time 0), what the plant's delayed command deviates from
    u_bar_delayed = acting_commands(u_bar, l, True) if per_channel else (
        jnp.concatenate([jnp.zeros((l, nd), dtype), u_bar])[:K] if l > 0 else u_bar)
    root_dt = jnp.sqrt(jnp.asarray(problem.dt, dtype))

    def point(z, x_bar, x_bar_next, ub, ubd, LMk, t):
        """Eq. P1 at one z = [dx_k, du_{k-m}, ..., du_{k-1}] [N]: (g_k(z) [N], G_k(z) [n, p],
        dt l(x_k, u_k))."""
        dx, sent = z[:nx], z[nx:].reshape(m, nd)
        x = x_bar + dx
        # the law of lqg.law.delayed_law, as a plain product: its kernel's custom JVP does
        # not nest, and the second-order rule differentiates twice
        du = LMk @ jnp.concatenate([dx, sent[m - l_p:].reshape(-1)])
        u = jnp.clip(ub + du, problem.u_min, problem.u_max)
        ud = acting_command(u, ubd, sent, l)
        x_next = x + problem.dt * problem.dynamics_at(x, u, ud, t)
        G = root_dt * problem.noise_at(x, u, ud, t) if problem.noise is not None else jnp.zeros((nx, 0), dtype)
        sent_next = jnp.concatenate([sent[1:], (u - ub)[None]]).reshape(-1) if m > 0 else sent.reshape(-1)
        return jnp.concatenate([x_next - x_bar_next, sent_next]), G, problem.dt * problem.cost.running(x, u, t)

    def sigma_step(mean, cov, args):
        """Eq. P2 with the expectations by the rule's points (eq. P4) in y = T_k z (eq. P5)."""
        LMk = args[4]                   # args: point's (x_bar, x_bar_next, u_bar, u_bar_delayed, LM_k, t)
        Z, w, rest = _sigma_points(mean, cov, rule, _inputs_map(nx, nd, l, l_p, m, LMk))
        Z_next, G, running = jax.vmap(point, in_axes=(0,) + (None,) * 6)(Z, *args)
        mean_next = w @ Z_next
        centred = Z_next - mean_next
        cov_next = jnp.einsum("i,ij,ik->jk", w, centred, centred)
        noise = jnp.einsum("i,ijp,ikp->jk", w, G, G)                  # E[G G']
        # the part y does not see only moves down the pending queue (eq. P5)
        shifted = rest[nx + nd:, nx + nd:]
        cov_next = cov_next.at[nx:nx + shifted.shape[0], nx:nx + shifted.shape[0]].add(shifted)
        return mean_next, cov_next.at[:nx, :nx].add(noise), w @ running

    def taylor_step(mean, cov, args):
        """Eq. P2 with the expectations of eq. P3."""
        def parts(z):
            z_next, G, running = point(z, *args)
            return z_next[:nx], G @ G.T, running
        z_next, G, running = point(mean, *args)
        J = jax.jacfwd(lambda z: point(z, *args)[0])(mean)               # [N, N]
        Hx, HGG, Hr = jax.hessian(parts)(mean)                           # [n, N, N], [n, n, N, N], [N, N]
        HP = Hx @ cov                                                    # [n, N, N]
        mean_next = z_next.at[:nx].add(0.5 * jnp.einsum("iab,ba->i", Hx, cov))
        cov_next = J @ cov @ J.T
        extra = 0.5 * jnp.einsum("iab,jba->ij", HP, HP) + G @ G.T + 0.5 * jnp.einsum("ijab,ba->ij", HGG, cov)
        return mean_next, cov_next.at[:nx, :nx].add(extra), running + 0.5 * jnp.sum(Hr * cov)

    def step(carry, data):
        mean, cov, total = carry
        moments = taylor_step if rule == "second_order" else sigma_step
        mean_next, cov_next, running = moments(mean, cov, data)
        cov_next = 0.5 * (cov_next + cov_next.T)
        return (mean_next, cov_next, total + running), (mean_next, cov_next)

    nz = nx + m * nd
    init = (jnp.zeros(nz, dtype), jnp.zeros((nz, nz), dtype), jnp.asarray(0.0, dtype))
    data = (policy.x_nominal[:-1], policy.x_nominal[1:], u_bar, u_bar_delayed, LM, problem.step_times(dtype))
    (mean, cov, total), (means, covs) = jax.lax.scan(step, init, data)
    final_cost = lambda z: problem.cost.final(policy.x_nominal[-1] + z[:nx], problem.final_time)
    if rule == "second_order":
        expected_final = final_cost(mean) + 0.5 * jnp.sum(jax.hessian(final_cost)(mean) * cov)
    else:
        Z, w, _ = _sigma_points(mean, cov, rule, jnp.eye(nx, nz, dtype=dtype))
        expected_final = w @ jax.vmap(final_cost)(Z)
    means = jnp.concatenate([init[0][None], means])
    covs = jnp.concatenate([init[1][None], covs])
    state = Prediction(policy.x_nominal + means[:, :nx], covs[:, :nx, :nx])
    return ClosedLoopPrediction(total + expected_final, state, Prediction(means, covs))


def _check_closure_input(entry_point: str, problem: Problem, policy: Policy, rule: str) -> None:
    """The checks of the closure's callers ([`closed_loop_prediction`][delayed_ilqr.prediction.closed_loop_prediction] and
    ``statistical.statistical_feedback``, ``entry_point`` as "module.function"): float64 on,
    full-state feedback, a known rule; a ``ValueError`` naming the function otherwise."""
    _precision.require_x64(entry_point)
    caller = entry_point.rsplit(".", 1)[-1]
    if problem.observation is not None or policy.estimator is not None:
        raise ValueError(f"{caller}: problem.observation must be None (full-state feedback) and the "
                         "policy must have no estimator")
    if rule not in RULES:
        raise ValueError(f"{caller}: rule must be one of {RULES}; got {rule!r}")


def closed_loop_prediction(problem: Problem, policy: Policy, rule: str = "second_order") -> ClosedLoopPrediction:
    """E[J] and the states' moments of ``policy`` on ``problem``'s nonlinear plant, as
    [`delayed_ilqr.simulate`][delayed_ilqr.simulate] runs it (``substeps=1``), by moment propagation (no sampling).

    The closed loop is a Markov chain in z_k = [dx_k; du_{k-m}; ...; du_{k-1}] (N = n + m d entries),
    m = max(l, l_p) (l the plant's delay, l_p the policy's; du the commands sent minus their
    nominal; with per-channel delays l = [l_1, ..., l_d], m = max(L, l_p) for the frame L and
    channel j acts with du_{k-l_j, j}):

        u_k = clip(u_bar_k + L_k dx_k + sum_i M_k^i du_{k+i-l_p}),   ud_k = u_{k-l} (u_k if l = 0)
        z_{k+1} = g_k(z_k) + [G_k(z_k) xi_k; 0],   xi_k ~ N(0, I_p)                          (P1)
        g_k(z) = [x_k + dt f(x_k, u_k, ud_k) - x_bar_{k+1}; du_{k-m+1}; ...; du_k],   G_k = sqrt(dt) F(x_k, u_k, ud_k)

    from z_0 = 0. As xi_k is independent of z_k, exactly:

        E[z_{k+1}] = E[g_k],   Cov(z_{k+1}) = Cov(g_k) + [E[G_k G_k'] 0; 0 0]
        E[J] = sum_k dt E[l(x_k, u_k)] + E[h(x_K)]                                            (P2)

    The expectations over z_k are taken as if z_k ~ N(mean_k, P_k) (the Gaussian closure), by
    ``rule``:

    - ``"second_order"`` (default): the Gaussian moments of each function's second-order Taylor
      expansion at the mean (J = dg/dz, H_i = d^2 g_i/dz^2 at mean_k; the same for G G' and l):

          E[g] = g(mean) + tr(H P) / 2,   Cov(g) = J P J' + [tr(H_i P H_j P)]_ij / 2          (P3)

    - ``"fifth_degree"``: Stroud's symmetric rule, exact for polynomials of degree <= 5 of a
      Gaussian: mean_k (weight 2 / (r+2)), mean_k +- sqrt(r+2) s_i ((4-r) / (2 (r+2)^2)) and
      mean_k + sqrt((r+2)/2) (+-s_i +- s_j), i < j (1 / (r+2)^2), with s_i the r columns of the
      root R_k of eq. P5; 2 r^2 + 1 points.
    - ``"cubature"``: mean_k +- sqrt(r) s_i, weights 1 / (2r) (degree 3). The points lie sqrt(r)
      standard deviations out: beyond degree 3 its answer depends on r and on the choice of root,
      not only on the plant (``docs/results/noise_calibration.md`` §2); the cheapest rule, for
      checks.                                                                                (P4)

    The sigma points live where the nonlinearity does. Everything nonlinear in P1 (f, the clip, F,
    l) is a function of r = n + 2d linear combinations y = T_k z of the N entries of z (n + d at
    l = 0): dx_k, the feedback's du_k and the delayed du_{k-l}. For a Gaussian z, z = mean_k +
    R_k eta + e with eta ~ N(0, I_r), e ~ N(0, E_k) independent of eta and T_k e = 0 (R_k = S W,
    E_k = S (I - W W') S', S the symmetric root of P_k and W the right singular vectors of T_k S),
    so g_k(z) = g_k(mean_k + R_k eta) + D e, D the shift of the pending queue, and:

        E[g_k] = E_eta[g_k(mean_k + R_k eta)],   Cov(g_k) = Cov_eta(g_k(mean_k + R_k eta)) + D E_k D'  (P5)

    exactly; the rules integrate over eta in r dimensions (all N when N <= r; the final cost over
    the n of dx_K). Their points then do not grow in number or reach with the delay: at l = 15 on
    the six-muscle arm, 969 fifth-degree points instead of 20001.

    On a linear plant with quadratic cost g is affine and G G', l and h quadratic: every rule is
    then exact (equal to [`delayed_ilqr.lqg.closed_loop_moments`][delayed_ilqr.lqg.closed_loop_moments] and
    [`policy_cost`][delayed_ilqr.lqg.policy_cost] of the policy's gains, whatever the law of z_k). On a
    nonlinear plant the rules capture the mean shift and covariance growth from the plant's
    curvature that [`predict`][delayed_ilqr.prediction.predict] and ``Solution.expected_cost`` leave out, but not what the
    Gaussian closure leaves out: signal-dependent noise makes z_k heavy-tailed
    (``docs/results/noise_calibration.md`` §2 measures both against Monte Carlo on the torque arm).

    Args:
        problem: the plant, full-state feedback (no observation).
        policy: a [`Policy`][delayed_ilqr.Policy] without estimator (e.g. ``solve(problem).policy``),
            run without its feedforward as [`simulate`][delayed_ilqr.simulate] runs it; its delay l_p
            may differ from the plant's.
        rule: ``"second_order"``, ``"fifth_degree"`` or ``"cubature"``.

    Returns:
        [`ClosedLoopPrediction`][delayed_ilqr.prediction.ClosedLoopPrediction]: expected_cost [], state mean [K+1, n] and cov [K+1, n, n],
        and z, the moments of the whole chain (P1): mean [K+1, N] and cov [K+1, N, N] of
        z_k = [dx_k; du_{k-m}; ...; du_{k-1}] (the clipped commands' deviations, oldest first).
        One compiled scan over time; cost per step O(n N^3) (second order), O(r^2) plant
        evaluations (fifth degree) and O(r) (cubature), r = min(n + 2d, N), plus O(N^3).

    Raises:
        ValueError: for a problem with an observation or a policy with an estimator, or an unknown
            rule.
    """
    _check_closure_input("prediction.closed_loop_prediction", problem, policy, rule)
    if not _delays.is_per_channel(problem.delay_steps):
        problem = problem.without_frame("closed_loop_prediction")
    return _closed_loop_prediction(problem, policy, rule)
