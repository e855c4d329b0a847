"""What the solver returns: the policy, the per-iteration trace, and exit statuses that say what to do."""
from __future__ import annotations

import enum
from typing import NamedTuple, Optional

import jax
import numpy as np

__all__ = ["Policy", "Estimator", "Status", "Trace", "Solution"]


class Estimator:
    """The delayed Kalman filter of a policy whose sensors are delayed and noisy.

    It runs on deviations from the policy's nominal (``docs/derivation.md`` §14):

        e_k     = (y_k - y_nominal_k) - H_k x_tilde_k                   innovation of the measurement
        x_del_k = x_tilde_k + Kd_k e_k                                  E[dx_{k-l_s} | I_k]
        x_hat_k = A_{k-1} x_hat_{k-1} + B0_{k-1} du_{k-1} + B1_{k-1} du_{k-1-l} + Kc_k e_k
        x_tilde_{k+1} = A_{k-l_s} x_del_k + B0_{k-l_s} du_{k-l_s} + B1_{k-l_s} du_{k-l_s-l}

    with du the commands actually sent minus their nominal, l the policy's motor delay and
    (A, B0, B1) the linearisation of the plant at the nominal; the policy's law acts on x_hat_k.

    Attributes:
        A: [K, n, n]; B0, B1: [K, n, d]: the model the estimates move with.
        H: [K, m, n] dh/dx at x_nominal_{k-l_s}; y_nominal: [K, m] h(x_nominal_{k-l_s}).
        delayed_gain: [K, n, m] Kd_k; current_gain: [K, n, m] Kc_k (rows k < l_s unused).
        error_covariance: [K+1, n, n] Cov(dx_k - x_hat_k) of the linearised closed loop (row K:
            the terminal state against its prediction from I_{K-1}), signal-dependent motor noise
            included (``lqg.output_feedback``); with additive noise it is the Kalman filter's
            Sigma_k = Cov(dx_k | I_k).
        sensory_delay: l_s, the delay the filter was designed for (static: a pytree's aux data).
            It may differ from the plant's (a design that ignores the sensory delay).
    """

    _arrays = ("A", "B0", "B1", "H", "y_nominal", "delayed_gain", "current_gain", "error_covariance")

    def __init__(self, A, B0, B1, H, y_nominal, delayed_gain, current_gain, error_covariance, sensory_delay: int):
        self.A, self.B0, self.B1, self.H, self.y_nominal = A, B0, B1, H, y_nominal
        self.delayed_gain, self.current_gain, self.error_covariance = delayed_gain, current_gain, error_covariance
        self.sensory_delay = sensory_delay

    def replace(self, **changes) -> "Estimator":
        fields = {name: getattr(self, name) for name in self._arrays + ("sensory_delay",)}
        fields.update(changes)
        return Estimator(**fields)

    @property
    def n_outputs(self) -> int:
        return self.H.shape[-2]

    def __repr__(self):
        return (f"Estimator(K={self.H.shape[-3]}, n={self.A.shape[-1]}, m={self.n_outputs}, "
                f"sensory_delay={self.sensory_delay})")


jax.tree_util.register_pytree_node(
    Estimator,
    lambda e: (tuple(getattr(e, name) for name in Estimator._arrays), e.sensory_delay),
    lambda ls, arrays: Estimator(*arrays, sensory_delay=ls))


class Policy(NamedTuple):
    """A delayed feedback controller around a nominal trajectory (eq. 6 in absolute terms).

    The command sent at step k is:

        u_k = u_nominal_k + L_k (x_k - x_nominal_k) + sum_i M_k^i (u_{k+i-l} - u_nominal_{k+i-l})

    where u_{k+i-l} are the commands actually sent earlier (zero, like their nominal, for negative
    indices), clipped to the problem's limits. ``feedforward`` is the LQG step that the solver would
    take next (about zero at convergence); [`delayed_ilqr.simulate`][delayed_ilqr.simulate] does not add it.

    Attributes:
        x_nominal: [K+1, n]; u_nominal: [K, d]; feedforward: [K, d] I_k; state_feedback: [K, d, n]
        L_k; delay_feedback: [K, l, d, d] M_k^i (index i multiplies the command sent at k+i-l).
        estimator: None when the controller sees the state; for a problem with an
            [`Observation`][delayed_ilqr.Observation], the [`Estimator`][delayed_ilqr.Estimator] whose estimate
            x_nominal_k + x_hat_k replaces x_k in the law above.
    """

    x_nominal: jax.Array
    u_nominal: jax.Array
    feedforward: jax.Array
    state_feedback: jax.Array
    delay_feedback: jax.Array
    estimator: Optional[Estimator] = None

    def save(self, path, problem=None, info=None) -> None:
        """Writes the policy to ``path`` (``.npz`` with a JSON header, [`delayed_ilqr.saving`][delayed_ilqr.saving]);
        ``problem`` (optional) records its dt and delay; [`delayed_ilqr.load`][delayed_ilqr.load] reads it back."""
        from .saving import save
        save(path, self, problem, info)


class Status(enum.IntEnum):
    """Exit statuses of [`delayed_ilqr.solve`][delayed_ilqr.solve]; ``Status.X.message`` says what to change.

    The two converged statuses are certified first-order points (``Options``, derivation §12);
    with noise, the others come with the nominal of lowest merit the solve met.
    """

    CONVERGED_GRADIENT = 0
    CONVERGED_COST = 1
    MAX_ITERATIONS = 2
    REGULARIZATION_LIMIT = 3
    NON_FINITE_ROLLOUT = 4
    NON_FINITE_INITIAL = 5
    NON_FINITE_GAINS = 6
    NON_FINITE_FILTER = 7
    INVALID_TRACED_INPUT = 8

    def __str__(self) -> str:         # print(sol.status) and f"{status}" show the name, not the code
        return self.name

    def __format__(self, spec: str) -> str:
        return format(self.name, spec)

    @property
    def converged(self) -> bool:
        return self in (Status.CONVERGED_GRADIENT, Status.CONVERGED_COST)

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    Status.CONVERGED_GRADIENT: "converged: the feedforward step is below Options.tol_grad (lambda < 1e-5)",
    Status.CONVERGED_COST: "converged: the cost reduction of the best step (or, without noise, the one the "
                           "model predicts) is below Options.tol_cost, and so is the Newton step's (lambda < 1e-5)",
    Status.MAX_ITERATIONS: "stopped at Options.max_iterations before converging; try increasing "
                           "max_iterations or a better u_init",
    Status.REGULARIZATION_LIMIT: "no descent: the regularisation exceeded Options.reg_max (H not positive "
                                 "definite or no step reduced the cost); check the cost's convexity in u, "
                                 "scale the problem, or try another u_init",
    Status.NON_FINITE_ROLLOUT: "the rollout of every trial step produced NaN or inf; the dynamics may blow up: "
                               "reduce dt, bound the controls, or start from a gentler u_init",
    Status.NON_FINITE_INITIAL: "the rollout of u_init is not finite (NaN or overflow) or its cost is not: "
                               "choose a u_init whose rollout stays bounded",
    Status.NON_FINITE_GAINS: "not converged: the backward pass at the last nominal gave NaN or inf gains; the "
                             "nominal and policy returned are those of the last backward pass whose gains were "
                             "finite (its expected_cost too); try another u_init, more regularisation "
                             "(Options.reg_init) or a cost that is convex in every direction the commands reach",
    Status.NON_FINITE_FILTER: "the delayed filter designed at the nominal is not finite (the observation's output "
                              "h, its noise G or their derivatives gave NaN or inf along the nominal); the policy "
                              "keeps the full-state feedback and a filter without measurement updates (zero "
                              "gains, finite stand-ins for the rest), and expected_cost is NaN: check h and G "
                              "at the nominal states",
    Status.INVALID_TRACED_INPUT: "nothing was solved: a traced argument (under jit or vmap) broke a rule that is "
                                 "checked when it is concrete: a delay_steps outside 0..delay_frame or "
                                 "not below the horizon, or limits with u_min >= u_max (or NaN) in some component; "
                                 "the nominal is the rollout of u_init with zero feedback",
}


class Trace(NamedTuple):
    """Per-iteration record, arrays of length ``max_iterations + 1``; entries past ``iterations`` are NaN.

    Attributes:
        cost: eq. (2) on the nominal (noise-free) trajectory after each iteration (index 0: u_init).
        merit: the noise-aware cost the line search minimises (equals ``cost`` without noise).
        expected_reduction: the LQG prediction for the accepted (or last tried) step.
        step_size: the accepted alpha (0 when no step was accepted).
        reg: the regularisation lambda used in the iteration's backward pass.
        grad_norm: Tassa's gradient measure, mean_k max_i |I_k,i| / (|u_k,i| + 1).
    """

    cost: jax.Array
    merit: jax.Array
    expected_reduction: jax.Array
    step_size: jax.Array
    reg: jax.Array
    grad_norm: jax.Array


class Solution(NamedTuple):
    """The result of [`delayed_ilqr.solve`][delayed_ilqr.solve].

    Attributes:
        x: [K+1, n] nominal states; u: [K, d] nominal commands.
        cost: eq. (2) on the nominal, noise-free trajectory.
        expected_cost: the local (linearised) prediction of E[J]: J(0) of the last LQG
            approximation at the nominal (noise terms included). With an observation: the exact
            expected cost of the controller acting on the delayed filter's estimate, on that
            linearisation (``lqg.output_feedback_cost``). It is exact for the linearised plant
            only; the plant's higher-order terms can make the Monte Carlo cost of
            `simulate` many times larger (``docs/results/noise_calibration.md``),
            so measure by Monte Carlo (`delayed_ilqr.statistics.prediction_warning`).
        status: the [`Status`][delayed_ilqr.Status] (an IntEnum: prints as its name, compares as its code); an
            int32 array of codes when the solve was traced (``jit``, ``vmap``).
        iterations: number of iterations run.
        policy: the [`Policy`][delayed_ilqr.Policy] (nominal trajectory and gains at the returned nominal).
        trace: the [`Trace`][delayed_ilqr.Trace].
    """

    x: jax.Array
    u: jax.Array
    cost: jax.Array
    expected_cost: jax.Array
    status: jax.Array
    iterations: jax.Array
    policy: Policy
    trace: Trace

    def save(self, path, problem=None, info=None) -> None:
        """Writes the solution (nominal, policy, trace, status) to ``path`` (``.npz`` with a JSON
        header, [`delayed_ilqr.saving`][delayed_ilqr.saving]); ``problem`` (optional) records its dt and delay;
        [`delayed_ilqr.load`][delayed_ilqr.load] reads it back."""
        from .saving import save
        save(path, self, problem, info)

    @property
    def converged(self):
        status = np.asarray(self.status)
        return (status == Status.CONVERGED_GRADIENT) | (status == Status.CONVERGED_COST) if status.ndim \
            else Status(int(status)).converged

    @property
    def message(self):
        status = np.asarray(self.status)
        if status.ndim:
            return [Status(int(s)).message for s in status.ravel()]
        return Status(int(status)).message
