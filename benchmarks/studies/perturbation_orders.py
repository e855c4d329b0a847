"""How much of the gap between the linearised prediction and Monte Carlo the
second- and third-order perturbations of the closed loop carry, without the Gaussian closure of
``prediction.closed_loop_prediction``.

On the same noise samples as ``simulate`` (seed 1), each trial runs, in the deviations
z = [dx, du_{k-l}, ..., du_{k-1}] of the noise-aware design's closed loop (g the plant's Euler
step in z with the feedback's commands unclipped, G its noise, xi_k the standard normal draw of
step k, D^j the j-th derivative at the nominal z = 0)::

    z1' = Dg[z1] + (G + DG[z1]) xi                       the linearised loop (the LQG's model)
    z2' = Dg[z2] + D^2 g[z1, z1] / 2                     the curvature, second order
    z3' = Dg[z3] + D^2 g[z1, z2] + D^3 g[z1, z1, z1] / 6 + (DG[z2] + D^2 G[z1, z1] / 2) xi

and the plant's own closed loop with the commands unclipped (z) and as ``simulate`` runs it
(clipped at the limits). Printed: the mean cost (+- standard error) of z1, z1 + z2,
z1 + z2 + z3, the unclipped plant and ``simulate``, each trial's cost scored exactly; and the
cost of z1 + z2 + z3 less its terms c''[z2, z3] + c''[z3, z3] / 2 (c'' the cost's second
derivative at the nominal; exact for a quadratic cost such as arm2's), the part of the third-order
expansion whose expectation needs moments of z1 of order four at most (z2 is quadratic in z1, z3
cubic): what a moment recursion truncated at the fourth moments could predict.

CASE: "arm2" (``arm2(delay=DELAY, noise=True, sigma_u=SIGMA_U_HUMAN)``, the demo's reach, default
options) or "muscle:J" (``arm2_muscle6`` to target J of ``center_out_targets(8, 0.1)``, the
center-out study's options).

    PYTHONPATH=src .venv/bin/python benchmarks/studies/perturbation_orders.py CASE DELAY TRIALS
    e.g. ... arm2 0.1 4000;  ... muscle:8 0.05 2000
"""
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr.lqg.law import augmented_feedback  # noqa: E402
from delayed_ilqr.lqg import Gains  # noqa: E402
from delayed_ilqr.models import arm2  # noqa: E402
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS  # noqa: E402
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN  # noqa: E402
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, arm2_muscle6, center_out_targets  # noqa: E402


def case(name: str, delay: float):
    """(problem, noise-aware solution) of CASE (module docstring)."""
    if name == "arm2":
        problem = arm2(delay=delay, noise=True, sigma_u=SIGMA_U_HUMAN)
        return problem, di.solve(problem)
    target = center_out_targets(8, 0.1)[int(name.split(":")[1]) - 1]
    problem = arm2_muscle6(**LI_TODOROV, delay=delay, target=tuple(target))
    return problem, di.solve(problem, options=DEFAULT_OPTIONS)


def main(argv):
    name, delay, n = argv[1], float(argv[2]), int(argv[3])
    problem, sol = case(name, delay)
    policy = sol.policy
    K, nx, nd, l, dt = problem.horizon, problem.n_states, problem.n_controls, problem.delay_steps, problem.dt
    LM = augmented_feedback(Gains(policy.feedforward, policy.state_feedback, policy.delay_feedback))
    u_bar = policy.u_nominal
    u_bar_delayed = jnp.concatenate([jnp.zeros((l, nd)), u_bar])[:K] if l > 0 else u_bar
    N = nx + l * nd

    def g(z, k):
        """The plant's step in deviations: (noise-free successor, sqrt(dt) F, running cost)."""
        dx, sent = z[:nx], z[nx:].reshape(l, nd)
        x = policy.x_nominal[k] + dx
        du = LM[k] @ z
        u = u_bar[k] + du
        ud = u_bar_delayed[k] + sent[0] if l > 0 else u
        x_next = x + dt * problem.dynamics(x, u, ud) - policy.x_nominal[k + 1]
        sent_next = jnp.concatenate([sent[1:], du[None]]).reshape(-1) if l > 0 else sent.reshape(-1)
        return jnp.concatenate([x_next, sent_next]), jnp.sqrt(dt) * problem.noise(x, u, ud), \
            dt * problem.cost.running(x, u)

    def trial(key):
        xi = jax.random.normal(key, (K, 1, problem.n_noise))[:, 0]      # simulate's draw, substeps = 1
        zero = jnp.zeros(N)

        def step(carry, k):
            z1, z2, z3, z = carry
            f = lambda v: g(v, k)[:2]
            (_, G0), (Az1, dG1) = jax.jvp(f, (zero,), (z1,))
            Q11, d2G11 = d(d(f, z1), z1)(zero)                            # D^2 (g, G)[z1, z1]
            Q12, _ = d(d(f, z2), z1)(zero)                                # D^2 g[z1, z2]
            T111, _ = d(d(d(f, z1), z1), z1)(zero)                        # D^3 g[z1, z1, z1]
            Az2, dG2 = jax.jvp(f, (zero,), (z2,))[1]
            Az3 = jax.jvp(f, (zero,), (z3,))[1][0]
            plant, F = f(z)
            z1_next = Az1.at[:nx].add((G0 + dG1) @ xi[k])
            z2_next = Az2 + 0.5 * Q11
            z3_next = (Az3 + Q12 + T111 / 6).at[:nx].add((dG2 + 0.5 * d2G11) @ xi[k])
            z_next = plant.at[:nx].add(F @ xi[k])
            running = lambda v: g(v, k)[2]
            return (z1_next, z2_next, z3_next, z_next), \
                (running(z1), running(z1 + z2), running(z1 + z2 + z3), sixth(running, z2, z3), running(z))

        def sixth(c, z2, z3):
            """c''[z2, z3] + c''[z3, z3] / 2: the terms of c(z1 + z2 + z3) of order five and six in z1."""
            c2 = lambda a, b: d(d(c, a), b)(zero)
            return c2(z2, z3) + 0.5 * c2(z3, z3)

        d = lambda h, v: (lambda w: jax.jvp(h, (w,), (v,))[1])         # w -> Dh(w)[v]
        (z1, z2, z3, z), (r1, r12, r123, r56, r) = jax.lax.scan(step, (zero,) * 4, jnp.arange(K))
        final = lambda v: problem.cost.final(policy.x_nominal[-1] + v[:nx])
        third = r123.sum() + final(z1 + z2 + z3)
        return (r1.sum() + final(z1), r12.sum() + final(z1 + z2), third,
                third - r56.sum() - sixth(final, z2, z3), r.sum() + final(z))

    costs = jax.jit(jax.vmap(trial))(jax.random.split(jax.random.PRNGKey(1), n))
    reference = np.asarray(di.simulate(problem, policy, n, seed=1).cost)
    print(f"{name}, delay {delay} s, {n} trials, solver {di.Status(int(sol.status)).name}; "
          f"predicted (linearised) {float(sol.expected_cost):.4g}")
    for label, c in zip(("linear loop z1", "second order z1 + z2", "third order z1 + z2 + z3",
                         "  its terms with moments of z1 to order four", "plant, commands unclipped",
                         "simulate (clipped)"),
                       [np.asarray(c) for c in costs] + [reference]):
        print(f"{label}: {c.mean():.4g} +- {c.std() / np.sqrt(c.size):.2g}")


if __name__ == "__main__":
    main(sys.argv)
