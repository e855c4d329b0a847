"""Issue 19 item 4: how much of the torque arm's gap between the linearised prediction and Monte
Carlo a second-order perturbation of the closed loop carries, without the Gaussian closure of
``prediction.closed_loop_prediction``.

On the same noise samples as ``simulate`` (seed 1), each trial runs, in the deviations
z = [dx, du_{k-l}, ..., du_{k-1}] of the noise-aware design's closed loop on
``arm2(delay=DELAY, noise=True, sigma_u=SIGMA_U_HUMAN)``:
z1 the linear closed loop with its signal-dependent noise (z1' = A z1 + (G + dG[z1]) xi),
z2' = A z2 + Q[z1, z1] / 2 (Q the second derivative of the plant's step at the nominal), and the
plant's own closed loop (a check: it equals ``simulate``). Printed: the mean cost (+- standard
error) of the linear loop (z1), of z1 + z2 and of the plant.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/arm2_perturbation_orders.py DELAY TRIALS
    e.g. ... 0.1 4000
"""
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr.ilqg.closed_loop import augmented_feedback  # noqa: E402
from delayed_ilqr.lqg import Gains  # noqa: E402
from delayed_ilqr.models import arm2  # noqa: E402
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN  # noqa: E402


def main(argv):
    delay, n = float(argv[1]), int(argv[2])
    problem = arm2(delay=delay, noise=True, sigma_u=SIGMA_U_HUMAN)
    sol = di.solve(problem)
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
            z1, z2, z = carry
            f = lambda v: g(v, k)
            (_, G0, _), (Az1, dG, _) = jax.jvp(f, (zero,), (z1,))
            Q = jax.jvp(lambda v: jax.jvp(f, (v,), (z1,))[1][0], (zero,), (z1,))[1]
            Az2 = jax.jvp(f, (zero,), (z2,))[1][0]
            plant, F, running = f(z)
            z1_next = Az1.at[:nx].add((G0 + dG) @ xi[k])
            z_next = plant.at[:nx].add(F @ xi[k])
            return (z1_next, Az2 + 0.5 * Q, z_next), (f(z1)[2], f(z1 + z2)[2], running)

        (z1, z2, z), (r1, r12, r) = jax.lax.scan(step, (zero, zero, zero), jnp.arange(K))
        final = lambda v: problem.cost.final(policy.x_nominal[-1] + v[:nx])
        return r1.sum() + final(z1), r12.sum() + final(z1 + z2), r.sum() + final(z)

    costs = jax.jit(jax.vmap(trial))(jax.random.split(jax.random.PRNGKey(1), n))
    reference = np.asarray(di.simulate(problem, policy, n, seed=1).cost)
    print(f"arm2, delay {delay} s, {n} trials; predicted (linearised) {float(sol.expected_cost):.4g}")
    for name, c in zip(("linear loop z1", "second-order z1 + z2", "plant", "simulate"),
                       [np.asarray(c) for c in costs] + [reference]):
        print(f"{name}: {c.mean():.4g} +- {c.std() / np.sqrt(c.size):.2g}")


if __name__ == "__main__":
    main(sys.argv)
