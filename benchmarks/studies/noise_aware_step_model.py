"""Why the slow noise-aware muscle reaches take small steps.

Runs one center-out reach of the convergence grid (``noise_aware_convergence.py``) iteration by
iteration with the solver's own loop body, records whether the feedback pattern (which commands get
feedback) changes between iterations, and at the last iterate compares the LQG model of the merit
along the step, alpha a + alpha^2 b, with the merit of the nonlinear rollouts: under the law
(closed loop, as the line search scores it) and under the law's linear plan applied open loop. It
also reports how far the open-loop nonlinear state deviation is from the linear one.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/noise_aware_step_model.py FACTOR DELAY TARGET ITERATIONS [WIDTH]
    e.g. ... 2 0.15 8 300 1e-3

WIDTH (optional) replaces ``models.muscle.SWITCH_WIDTH`` for the run (the smoothing of the
activation switch; derivation §12, cause 4).
"""
import dataclasses
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from noise_aware_convergence import DEFAULT_SIGMA, problems  # noqa: E402

from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS  # noqa: E402
from delayed_ilqr.ilqg import solver  # noqa: E402
from delayed_ilqr.ilqg.backward import backward  # noqa: E402
from delayed_ilqr.ilqg.bounded import linear_plan, model_cost  # noqa: E402
from delayed_ilqr.ilqg.line_search import candidate_scores, merit  # noqa: E402
from delayed_ilqr.ilqg.linearize import delayed_commands, linearize, rollout, trajectory_cost  # noqa: E402
from delayed_ilqr.lqg.frame import SlotGains  # noqa: E402
from delayed_ilqr.models import muscle  # noqa: E402
from delayed_ilqr.models.metadata import default_u_init  # noqa: E402

ALPHAS = (0.0, 0.004, 0.008, 0.016, 0.03, 0.06, 0.125, 0.25, 0.5, 1.0)


def initial_state(problem, u_init, options):
    """The solver's state before its first iteration (as ``solver._solve_body`` builds it)."""
    xs = rollout(problem, u_init)
    K, nx, nd, l = problem.horizon, problem.n_states, problem.n_controls, problem.delay_steps
    nan = jnp.full(3, jnp.nan)
    latch = solver._Latch(jnp.zeros((K, nd), bool), jnp.zeros((K, nd), jnp.int32), jnp.asarray(0, jnp.int32),
                          jnp.zeros((K, nd), bool), jnp.asarray(jnp.inf), jnp.asarray(-jnp.inf), jnp.full(2, jnp.nan))
    return solver._State(u_init, xs, trajectory_cost(problem, xs, u_init), jnp.asarray(options.reg_init),
                         jnp.asarray(1.0), jnp.asarray(0, jnp.int32), jnp.asarray(solver._RUNNING, jnp.int32),
                         jnp.asarray(False), SlotGains(jnp.zeros((K, nd)), jnp.zeros((K, nd, nx + l * nd))),
                         jnp.asarray(jnp.nan), solver.Trace(nan, nan, nan, nan, nan, nan), latch,
                         solver._Best(u_init, xs, trajectory_cost(problem, xs, u_init), jnp.asarray(jnp.inf)))


def main(argv):
    factor, delay, target, iterations = float(argv[1]), float(argv[2]), int(argv[3]), int(argv[4])
    if len(argv) > 5:
        muscle.SWITCH_WIDTH = float(argv[5])
    problem = problems("muscle", factor * DEFAULT_SIGMA["muscle"], delay)[target - 1]
    options = dataclasses.replace(DEFAULT_OPTIONS, max_iterations=10 ** 6)

    @jax.jit
    def one(st):
        # the counter runs 0, 1, 1, ...: a three-entry trace, and the latch counts from the second pass on
        # (with the counter kept at 0 it never would)
        it = jnp.minimum(st.iteration, 1)
        new = solver._iteration(problem, options, st._replace(iteration=it))
        return new, new.trace.merit[it + 1], new.trace.step_size[it + 1]

    st = initial_state(problem, jnp.asarray(default_u_init(problem)), options)
    previous, changes, alphas = None, [], []
    for _ in range(iterations):
        st, _, alpha = one(st)
        if int(st.status) != solver._RUNNING:       # stopped: the analysis below is at the last nominal
            print(f"the solver stopped ({solver.Status(int(st.status)).name}) after {len(alphas) + 1} iterations")
            break
        mask = np.asarray(solver._feedback_mask(st.gains))
        changes.append(0 if previous is None else int(np.sum(mask != previous)))
        alphas.append(float(alpha))
        previous = mask
    last = len(alphas) // 5
    print(f"{len(alphas)} iterations; feedback-pattern changes in the last {last}: {sum(changes[-last:])}; "
          f"latched commands: {int(np.sum(np.asarray(st.latch.held)))}; "
          f"median step size of the last {last}: {np.median(alphas[-last:]):.3g}; lambda now {float(st.reg):.2g}")

    bp = backward(problem, st.xs, st.us, 0.0, options.method, options.limit_margin, st.latch.held)
    lqg = linearize(problem, st.xs, st.us)
    plan = linear_plan(lqg, bp.gains)
    _, m0 = merit(problem, st.xs, st.us, bp.S, st.xs)
    a, b = bp.predicted
    alphas = jnp.asarray(ALPHAS)
    _, closed, _ = candidate_scores(problem, st.xs, st.us, bp.gains, alphas, bp.S)
    open_loop = SlotGains(plan, jnp.zeros_like(bp.gains.feedback))
    opened_cost, opened, _ = candidate_scores(problem, st.xs, st.us, open_loop, alphas, bp.S)
    u = np.asarray(st.us)
    print(f"merit {float(m0):.10e}; plan: max |du| {float(jnp.max(jnp.abs(plan))):.2e}, leaves the box at alpha = 1: "
          f"{int(np.sum((u + np.asarray(plan) < problem.u_min) | (u + np.asarray(plan) > problem.u_max)))} commands")
    print("| alpha | model a alpha + b alpha^2 | closed loop (line search) | open-loop plan |")
    print("|---|---|---|---|")
    for al, c, o in zip(ALPHAS, np.asarray(closed - m0), np.asarray(opened - m0)):
        print(f"| {al:g} | {float(al * a + al * al * b):+.3e} | {c:+.3e} | {o:+.3e} |")

    # the open-loop plan's state deviation: nonlinear rollout against the linear model
    du = np.asarray(plan)
    dud = np.asarray(delayed_commands(problem, plan))
    A, B0, B1 = (np.asarray(m) for m in (lqg.A, lqg.B0, lqg.B1))
    dx, linear = np.zeros(problem.n_states), [np.zeros(problem.n_states)]
    for k in range(problem.horizon):
        dx = A[k] @ dx + B0[k] @ du[k] + B1[k] @ dud[k]
        linear.append(dx)
    linear = np.array(linear)
    nonlinear = np.asarray(rollout(problem, st.us + plan) - st.xs)
    print("largest |dx| per state, linear:", np.array2string(np.abs(linear).max(0), precision=2))
    print("largest |nonlinear - linear| per state:", np.array2string(np.abs(nonlinear - linear).max(0), precision=2))
    # the cost gradient times that residual: the second-order dynamics term that the LQG (Gauss-Newton)
    # leaves out and DDP's s'f_zz would add
    residual = nonlinear - linear
    print(f"first-order cost of the residual, 2 sum_k d_k'(dx_nonlinear - dx_linear): "
          f"{2 * float(np.sum(np.asarray(lqg.d) * residual)):+.3e} (open-loop merit change at alpha = 1 minus "
          f"the model's: {float(opened[-1] - m0 - (a + b)):+.3e})")
    # the same change split into the cost (2) and the noise cost sum c'S c, each against its model
    cost_model = float(model_cost(lqg, plan))
    c0 = float(trajectory_cost(problem, st.xs, st.us))
    print(f"at alpha = 1, open loop: cost (2) change {float(opened_cost[-1]) - c0:+.3e} (model {cost_model:+.3e}); "
          f"noise-cost change {float(opened[-1] - opened_cost[-1]) - (float(m0) - c0):+.3e} "
          f"(model {float(a + b) - cost_model:+.3e})")


if __name__ == "__main__":
    main(sys.argv)
