"""Why the torque arm's Monte Carlo mean leaves the prediction at 100 ms.

For the noise-aware design of ``arm2(delay=DELAY, noise=True, sigma_u=SIGMA_U_HUMAN)`` (the demo's
plant at the human noise level) it compares, on the same returned policy and seed:
``pred`` = ``Solution.expected_cost``; ``exact`` = ``lqg.policy_cost`` of the policy's gains
(feedforward 0, as ``simulate`` runs it) on the LQG at the nominal; ``linMC`` = ``lqg.simulate_lqg``
of that linear closed loop; ``MC`` = ``simulate`` on the plant; ``MC frozen`` = ``simulate`` on the
plant with the noise F evaluated at the nominal states, as the LQG has it (erratum N14); and the
RMS joint deviations from the nominal over time, linear against nonlinear.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/arm2_prediction_gap.py DELAY TRIALS
    e.g. ... 0.1 4000
"""
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr import lqg  # noqa: E402
from delayed_ilqr.ilqg.linearize import linearize  # noqa: E402
from delayed_ilqr.models import arm2  # noqa: E402
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN  # noqa: E402


def mean_and_se(c):
    return f"{c.mean():.5g} +- {c.std() / np.sqrt(c.size):.2g} (median {np.median(c):.4g})"


def main(argv):
    delay, n = float(argv[1]), int(argv[2])
    problem = arm2(delay=delay, noise=True, sigma_u=SIGMA_U_HUMAN)
    sol = di.solve(problem)
    model = linearize(problem, sol.x, sol.u)
    policy = sol.policy
    gains = lqg.Gains(jnp.zeros_like(policy.feedforward), policy.state_feedback, policy.delay_feedback)
    linear = lqg.simulate_lqg(model, gains, n, seed=1)
    runs = di.simulate(problem, policy, n, seed=1)
    nominal_x, f, F = sol.x, problem.dynamics, problem.noise
    frozen = problem.replace(dynamics=lambda x, u, ud, t: f(x, u, ud),
                             noise=lambda x, u, ud, t: F(nominal_x[jnp.round(t / problem.dt).astype(int)], u, ud),
                             time_dependent=True)
    frozen_runs = di.simulate(frozen, policy, n, seed=1)
    print(f"{problem.name}, delay {delay} s, {n} trials; nominal cost {float(sol.cost):.5g}")
    print(f"pred {float(sol.expected_cost):.5g}; exact {float(lqg.policy_cost(model, gains)):.5g}")
    print("linMC", mean_and_se(np.asarray(linear.cost)))
    print("MC", mean_and_se(np.asarray(runs.cost)))
    print("MC frozen", mean_and_se(np.asarray(frozen_runs.cost)))
    dx_nonlinear = np.asarray(runs.x) - np.asarray(sol.x)[None]
    dx_linear = np.asarray(linear.dx)
    print("| step | RMS dq linear [rad] | RMS dq nonlinear | RMS dq/dt linear [rad/s] | RMS dq/dt nonlinear |")
    print("|---|---|---|---|---|")
    rms = lambda a: np.array2string(np.sqrt(np.mean(a ** 2, axis=0)), precision=4)
    for k in range(0, problem.horizon + 1, 5):
        print(f"| {k} | {rms(dx_linear[:, k, :2])} | {rms(dx_nonlinear[:, k, :2])} | {rms(dx_linear[:, k, 2:])} | "
              f"{rms(dx_nonlinear[:, k, 2:])} |")


if __name__ == "__main__":
    main(sys.argv)
