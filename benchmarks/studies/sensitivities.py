"""Sensitivities of the noisy arm's optimal reach to delay and noise (docs/sensitivities.md).

For each delay: the noise-aware solve of P2-noisy, the derivative of its expected cost and of its
deterministic cost with respect to the noise scale sigma_u (implicit differentiation through the
solve, docs/derivation.md §16), and the Monte Carlo endpoint spread of its policy on the nonlinear
plant. The delay is a whole number of steps, so its effect is a finite difference across delays.
Writes docs/img/sensitivities.png and prints the table the page quotes.

Run: .venv/bin/python benchmarks/studies/sensitivities.py
"""
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.experiments.engine import monte_carlo
from delayed_ilqr.models import arm2

DELAYS = (0.0, 0.02, 0.04, 0.06, 0.08)
TRIALS = 400
OUT = Path(__file__).resolve().parents[2] / "docs" / "img" / "sensitivities.png"


def main():
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    rows = []
    print(f"{'delay':>6} {'status':>16} {'cost':>10} {'expected':>10} {'dE/dsigma':>10} {'dJ/dsigma':>10} "
          f"{'endpoint RMS':>13}")
    for delay in DELAYS:
        problem = arm2(delay=delay, noise="benchmark")

        def costs(p):
            sol = di.solve(p)
            return jnp.stack([sol.expected_cost, sol.cost]), sol

        # one reverse-mode pass per output (jacrev), both with respect to every array of the problem
        grad, sol = jax.jit(jax.jacrev(costs, has_aux=True))(problem)
        d_expected, d_cost = (float(v) for v in grad.noise.sigma_u)
        expected = sol.expected_cost
        errors = monte_carlo(problem, sol.policy, TRIALS, seed=0).errors
        rms = float(np.sqrt(np.mean(errors ** 2)))
        status = di.Status(int(sol.status))
        rows.append((delay, float(sol.cost), float(expected), d_expected, d_cost, rms, status.converged))
        print(f"{delay:6.2f} {status.name:>16} {float(sol.cost):10.4f} {float(expected):10.4f} {d_expected:10.4f} "
              f"{d_cost:10.4f} {rms * 1e3:10.2f} mm")
    plot(np.array(rows))


def plot(rows):
    from matplotlib.figure import Figure
    delay_ms, cost, expected, d_expected, d_cost, rms = (rows[:, i] for i in range(6))
    delay_ms = delay_ms * 1e3
    sigma = arm2(noise=True).noise.sigma_u
    fig = Figure(figsize=(11, 3.4), layout="constrained")
    ax = fig.add_subplot(1, 3, 1)
    ax.plot(delay_ms, expected, "o-", label="expected cost")
    ax.plot(delay_ms, cost, "s--", label="cost of the nominal (2)")
    for x, y, slope in zip(delay_ms, expected, np.gradient(expected, delay_ms)):
        ax.plot([x - 4, x + 4], [y - 4 * slope, y + 4 * slope], "k-", lw=0.8)
    ax.set(xlabel="delay (ms)", ylabel="cost", title="cost against delay (finite differences)")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(1, 3, 2)
    ax.plot(delay_ms, d_expected, "o-", label="d expected / d sigma_u")
    ax.plot(delay_ms, d_cost, "s--", label="d cost / d sigma_u")
    ax.set(xlabel="delay (ms)", ylabel="derivative", title=f"sensitivity to the noise scale (sigma_u = {sigma})")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(1, 3, 3)
    ax.plot(delay_ms, rms * 1e3, "o-")
    ax.set(xlabel="delay (ms)", ylabel="RMS hand error at the end (mm)",
           title=f"endpoint spread ({TRIALS} trials)")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=110)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
