"""What the solver returns: the policy, the per-iteration trace, and exit statuses that say what to do."""
from __future__ import annotations

import enum
from typing import NamedTuple

import jax
import numpy as np

__all__ = ["Policy", "Status", "Trace", "Solution"]


class Policy(NamedTuple):
    """A delayed feedback controller around a nominal trajectory (eq. 6 in absolute terms).

    The command sent at step k is::

        u_k = u_nominal_k + L_k (x_k - x_nominal_k) + sum_i M_k^i (u_{k+i-l} - u_nominal_{k+i-l})

    where u_{k+i-l} are the commands actually sent earlier (zero, like their nominal, for negative
    indices), clipped to the problem's limits. ``feedforward`` is the LQG step that the solver would
    take next (about zero at convergence); :func:`delayed_ilqr.simulate` does not add it.

    Attributes:
        x_nominal: [K+1, n]; u_nominal: [K, d]; feedforward: [K, d] I_k; state_feedback: [K, d, n]
        L_k; delay_feedback: [K, l, d, d] M_k^i (index i multiplies the command sent at k+i-l).
    """

    x_nominal: jax.Array
    u_nominal: jax.Array
    feedforward: jax.Array
    state_feedback: jax.Array
    delay_feedback: jax.Array


class Status(enum.IntEnum):
    """Exit statuses of :func:`delayed_ilqr.solve`; ``Status.X.message`` says what to change.

    The two converged statuses are certified first-order points (``Options``, derivation §12);
    with noise, the others come with the nominal of lowest merit the solve met.
    """

    CONVERGED_GRADIENT = 0
    CONVERGED_COST = 1
    MAX_ITERATIONS = 2
    REGULARIZATION_LIMIT = 3
    NON_FINITE_ROLLOUT = 4
    NON_FINITE_INITIAL = 5

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
    """The result of :func:`delayed_ilqr.solve`.

    Attributes:
        x: [K+1, n] nominal states; u: [K, d] nominal commands.
        cost: eq. (2) on the nominal, noise-free trajectory.
        expected_cost: J(0) of the last LQG approximation (noise terms included).
        status: the :class:`Status` (an IntEnum: prints as its name, compares as its code); an
            int32 array of codes when the solve was traced (``jit``, ``vmap``).
        iterations: number of iterations run.
        policy: the :class:`Policy` (nominal trajectory and gains at the returned nominal).
        trace: the :class:`Trace`.
    """

    x: jax.Array
    u: jax.Array
    cost: jax.Array
    expected_cost: jax.Array
    status: jax.Array
    iterations: jax.Array
    policy: Policy
    trace: Trace

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
