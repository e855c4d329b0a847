"""Noise-aware reaches of the six-muscle arm that once failed to converge now do (the latch and
the activation switch of derivation §12). In a file of their own, apart from test_convergence.py's
first-order checks: each compiles and solves the muscle arm at another delay, and ``make test``
runs files, not tests, in parallel."""
import pytest

import delayed_ilqr as di


# the latch case in the suite; the other two (one compiled solve per delay) under make bench
@pytest.mark.parametrize("sigma_u, delay, k", [(0.005, 0.05, 3), pytest.param(0.01, 0.1, 6, marks=pytest.mark.full),
                                              pytest.param(0.005, 0.15, 7, marks=pytest.mark.full)])
def test_noisy_muscle_reaches_that_did_not_converge_now_do(sigma_u, delay, k):
    """Three reaches of the convergence grid (docs/results/noise_aware_convergence.md): the first cycled
    with period 9 at lambda = 0 (a command's feedback switching on and off: the latch), the
    second stopped "converged" under lambda = 1e5 (an excitation at its bound planned with half
    its derivative, then optima on the activation switch's kink), the third latched 89 commands
    while its merit still wandered over a factor 2 and then crept for 250 iterations (the latch
    fires only on a recurring window, LATCH_RECUR)."""
    from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, arm2_muscle6, center_out_targets, rest_commands
    problem = arm2_muscle6(delay=delay, target=tuple(center_out_targets()[k]), noise=True, sigma_u=sigma_u,
                           **LI_TODOROV)
    sol = di.solve(problem, rest_commands(problem), di.Options(max_iterations=300))
    assert sol.converged, sol.status
    n = int(sol.iterations)
    assert float(sol.trace.reg[n]) < 1e-5
