"""Issue 19: feedback gains re-designed by statistical linearisation (SL) of the plant around the
closed loop's predicted distribution, instead of around the nominal
(``docs/results/noise_calibration.md`` §5.3 and §5.5).

The solver's gains are those of the LQG linearised at the nominal (x_bar, u_bar). When the closed
loop's deviations leave the range of that linearisation (the six-muscle arm at 50-100 ms,
§5.1-5.4), the LQG's model is wrong where the trials are. SL keeps the nominal and replaces the
LQG's dynamics matrices by their expectations under the closed loop's own distribution, then
re-solves for the gains, to a fixed point. With the policy's gains G = (I, L, M) and its closed
loop z_k = [dx_k; du_{k-l}; ...; du_{k-1}] (deviations from the nominal, the clipped commands'):

  1. moments of z_k under G: (mean_k, P_k) = ``prediction.closed_loop_prediction(problem, G, rule).z``
     (the nonlinear closed loop under the Gaussian closure, eq. P1-P4 there);
  2. expected Jacobians of the Euler step x' = x + dt f(x, u, ud) over z_k ~ N(mean_k, P_k), by
     the rule's sigma points Z_i, w_i (``prediction._sigma_points``)::

         x_i = x_bar_k + dx_i,  u_i = clip(u_bar_k + [L_k M_k] Z_i),  ud_i = u_bar_{k-l} + du_{k-l,i}
         A_k = sum_i w_i (I + dt f_x(x_i, u_i, ud_i)),   B0_k = sum_i w_i dt f_u(.),
         B1_k = sum_i w_i dt f_ud(.)                                                      (SL1)

     (ud_i = u_i at l = 0); the noise terms (c, C0, C1) and the cost terms stay those of the
     nominal's linearisation (``ilqg.linearize.linearize``);
  3. the gains G_new of that LQG by the solver's backward pass and gain rule: Theorem 1's
     structured scan with ``lqg.gains.boxed_gains`` (margin ``Options.limit_margin``, bounds
     u_min - u_bar_k, u_max - u_bar_k) for a plant with limits, ``unconstrained_gains`` without,
     wrapped in ``unregularized_feedback`` with noise; lambda = 0; the nominal is not moved;
  4. G <- relax G_new + (1 - relax) G (I, L and M alike); the relative change of the feedback
     ||[L M]_new - [L M]|| / ||[L M]|| (Frobenius over all steps) says whether G is a fixed point.
                                                                                          (SL2)

ITERS such iterations start from the noise-aware solver solution. Each of the deterministic
design (``experiments.designs``' "deterministic": the plant without its noise, run in the noise),
the noise-aware design and the SL policy is run ``TRIALS`` times on the plant
(``simulate``, seed 0, the feedforward not applied). SL's own predictions of its cost: the exact
expected cost of its gains on its LQG (``lqg.policy_cost``, feedforward 0) and the Gaussian
closure's (``closed_loop_prediction``, ``rule``).

The solver's feedback latch (commands held without feedback, derivation §12) is not part of a
Solution: it is recovered as the commands the pass on the nominal's LQG gives feedback and the
solver's policy does not (grown to a fixed point), and held in every SL pass ("latch"; "repro", the relative difference of
that pass's feedback from the solver's, checks the recovery).

Not done: the nominal and feedforward are not re-optimised with the SL model, and the noise and
cost terms are not averaged.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/statistical_linearisation.py CASES TRIALS ITERS RULE RELAX [SEEDS]
    e.g. ... muscle:50:8,muscle:50:6,muscle:100:8,arm2:100 2000 8 fifth_degree 0.5
         ... muscle:50:8 2000 8 fifth_degree 0.5 0,1,2,3,4   (also each design's MC mean under these seeds)

CASES: model:delay_ms[:target], model "muscle" (``arm2_muscle6`` center-out reach to target
1-8 of ``center_out_targets(8, 0.1)``, the center-out study's design options) or "arm2"
(``arm2(noise=True, sigma_u=SIGMA_U_HUMAN)``, the demo's reach, default options);
"muscle:50:all" runs the 8 targets and adds their pooled mean.
"""
import sys
import time
from functools import partial

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr import Options  # noqa: E402
from delayed_ilqr.experiments import designs  # noqa: E402
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS  # noqa: E402
from delayed_ilqr.experiments.engine import solve_batch, take  # noqa: E402
from delayed_ilqr.ilqg.closed_loop import augmented_feedback  # noqa: E402
from delayed_ilqr.ilqg.linearize import delayed_commands, linearize  # noqa: E402
from delayed_ilqr.lqg import Gains, policy_cost  # noqa: E402
from delayed_ilqr.lqg.frame import from_slots  # noqa: E402
from delayed_ilqr.lqg.gains import boxed_gains, unconstrained_gains, unregularized_feedback  # noqa: E402
from delayed_ilqr.lqg.structured import structured_slot_scan  # noqa: E402
from delayed_ilqr.models import arm2  # noqa: E402
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN  # noqa: E402
from delayed_ilqr.models.arm2_muscle6 import arm2_muscle6, center_out_targets  # noqa: E402
from delayed_ilqr.prediction import _sigma_points, closed_loop_prediction  # noqa: E402
from delayed_ilqr.statistics import divergence_bound, diverged_trials, sample_stats  # noqa: E402


def gains_of(policy) -> Gains:
    return Gains(policy.feedforward, policy.state_feedback, policy.delay_feedback)


@partial(jax.jit, static_argnames=("rule",))
def expected_jacobians(problem, policy, z_mean, z_cov, rule: str):
    """Eq. SL1: A [K, n, n], B0 [K, n, d], B1 [K, n, d], each step's Jacobians of the Euler step
    averaged over the rule's points of z_k ~ N(z_mean [K+1, N][k], z_cov [K+1, N, N][k]),
    at the points' actual states and (clipped) commands, as ``closed_loop_prediction`` runs them."""
    nx, nd, l, dt = problem.n_states, problem.n_controls, problem.delay_steps, problem.dt
    eye = jnp.eye(nx, dtype=z_mean.dtype)

    def at_point(z, x_bar, u_bar, u_bar_delayed, LMk, t):
        x = x_bar + z[:nx]
        u = jnp.clip(u_bar + LMk @ z, problem.u_min, problem.u_max)
        ud = u_bar_delayed + z[nx:nx + nd] if l > 0 else u          # du_{k-l}: the oldest pending
        fx, fu, fud = jax.jacrev(lambda *a: problem.dynamics_at(*a, t), argnums=(0, 1, 2))(x, u, ud)
        return eye + dt * fx, dt * fu, dt * fud

    def step(row):
        mean, cov, *args = row
        Z, w = _sigma_points(mean, cov, rule)
        A, B0, B1 = jax.vmap(at_point, in_axes=(0,) + (None,) * 5)(Z, *args)
        return tuple(jnp.tensordot(w, J, axes=1) for J in (A, B0, B1))

    LM = augmented_feedback(gains_of(policy))
    rows = (z_mean[:-1], z_cov[:-1], policy.x_nominal[:-1], policy.u_nominal,
            delayed_commands(problem, policy.u_nominal), LM, problem.step_times(z_mean.dtype))
    return jax.lax.map(step, rows)


def backward_gains(problem, lqg, u_bar, limit_margin, held=None) -> Gains:
    """Step 3 of SL2: the gains of ``lqg`` by the solver's structured pass and gain rule
    (``ilqg.backward.backward`` with lambda = 0 and the feedback latch ``held`` [K, d] bool, None:
    none)."""
    gains_fn, bounds = unconstrained_gains, None
    if problem.has_limits:
        gains_fn, bounds = partial(boxed_gains, margin=limit_margin), (problem.u_min - u_bar, problem.u_max - u_bar)
        bounds += () if held is None else (held,)
    if problem.noise is not None:
        gains_fn = unregularized_feedback(gains_fn)
    slots, _, _ = structured_slot_scan(lqg, 0.0, store_value=False, gains_fn=gains_fn, bounds=bounds, store_S=False)
    return from_slots(slots, problem.n_states)


def feedback_rows(gains: Gains):
    """[K, d] bool: the commands with a nonzero feedback row."""
    return jnp.any(augmented_feedback(gains) != 0, axis=-1)


@jax.jit
def solver_latch(problem, policy, limit_margin):
    """The solver's feedback latch, which a Solution does not return, recovered: (held [K, d], the
    relative difference between the solver's feedback and the backward pass's on the nominal's own
    LQG with that latch). held grows from none by the commands without feedback in the solver's
    policy that the pass with the latch so far gives feedback (holding one command frees others
    upstream), until none is left; the difference is then round-off unless the solver's last pass
    was regularised where H is not positive definite."""
    nominal = linearize(problem, policy.x_nominal, policy.u_nominal)
    without = ~feedback_rows(gains_of(policy))

    def grow(state):
        held, _ = state
        more = held | (feedback_rows(backward_gains(problem, nominal, policy.u_nominal, limit_margin, held)) & without)
        return more, jnp.any(more != held)

    held, _ = jax.lax.while_loop(lambda state: state[1], grow, (jnp.zeros_like(without), jnp.asarray(True)))
    again = backward_gains(problem, nominal, policy.u_nominal, limit_margin, held)
    F_old, F_new = augmented_feedback(gains_of(policy)), augmented_feedback(again)
    return held, jnp.linalg.norm(F_new - F_old) / jnp.linalg.norm(F_old)


@partial(jax.jit, static_argnames=("rule",))
def sl_iteration(problem, policy, held, limit_margin, relax, rule: str):
    """One iteration of SL2 with the solver's latch ``held`` [K, d]: (the relaxed policy, the
    relative change of the feedback, the SL model's exact expected cost of the current gains,
    their closure prediction)."""
    nominal = linearize(problem, policy.x_nominal, policy.u_nominal)
    closure = closed_loop_prediction(problem, policy, rule)
    A, B0, B1 = expected_jacobians(problem, policy, closure.z.mean, closure.z.cov, rule)
    model = nominal.replace(A=A, B0=B0, B1=B1)
    old = gains_of(policy)
    new = backward_gains(problem, model, policy.u_nominal, limit_margin, held)
    F_old, F_new = augmented_feedback(old), augmented_feedback(new)
    change = jnp.linalg.norm(F_new - F_old) / jnp.linalg.norm(F_old)
    relaxed = jax.tree_util.tree_map(lambda a, b: relax * a + (1 - relax) * b, new, old)
    lqg_cost = policy_cost(model, old._replace(feedforward=jnp.zeros_like(old.feedforward)))
    return policy._replace(**relaxed._asdict()), change, lqg_cost, closure.expected_cost


def statistical_linearisation(problem, policy, held, iters, rule, relax, limit_margin):
    """ITERS iterations of SL2 from ``policy``: (policy, last change, the SL model's exact expected
    cost and closure prediction of the returned gains, log of (change, lqg cost, closure) per iteration)."""
    log = []
    for _ in range(iters):
        policy, change, lqg_cost, closure = sl_iteration(problem, policy, held, limit_margin, relax, rule)
        log.append((float(change), float(lqg_cost), float(closure)))
    # the predictions of the returned (relaxed) gains: one more evaluation, its step discarded
    _, _, lqg_cost, closure = sl_iteration(problem, policy, held, limit_margin, relax, rule)
    return policy, log[-1][0], float(lqg_cost), float(closure), log


def designs_of(model: str, delay_ms: float, targets):
    """[(label, plant, deterministic policy, noise-aware policy, limit margin)] for the targets."""
    delay = delay_ms / 1e3
    if model == "arm2":
        plant = arm2(delay=delay, noise=True, sigma_u=SIGMA_U_HUMAN)
        det_problem, options = designs.design(plant, "deterministic", Options())
        return [("-", plant, di.solve(det_problem).policy, di.solve(plant).policy, options.limit_margin)]
    points = center_out_targets(8, 0.1)
    plants = [arm2_muscle6(delay=delay, target=tuple(points[j - 1])) for j in targets]
    policies = {}
    for name in ("deterministic", "noise-aware"):
        problems = [designs.design(p, name, DEFAULT_OPTIONS)[0] for p in plants]
        sols = solve_batch(problems, DEFAULT_OPTIONS)
        policies[name] = [take(sols.policy, i) for i in range(len(plants))]
        statuses = [di.Status(int(s)).name for s in np.asarray(sols.status)]
        print(f"  {name} design at {delay_ms:g} ms: {statuses}", flush=True)
    return [(str(j), plant, policies["deterministic"][i], policies["noise-aware"][i], DEFAULT_OPTIONS.limit_margin)
            for i, (j, plant) in enumerate(zip(targets, plants))]


def monte_carlo(plant, policy, trials, seed=0):
    cost = np.asarray(di.simulate(plant, policy, trials, seed=seed).cost)
    return cost, sample_stats(cost, diverged_trials(cost, divergence_bound(plant)))


def cell(stats):
    low, high = stats.ci95
    div = f", {stats.n_diverged} div." if stats.n_diverged else ""
    return f"{stats.mean:.3g} [{low:.3g}, {high:.3g}{div}]"


def run_case(model, delay_ms, targets, trials, iters, rule, relax, pooled, seeds):
    for label, plant, det, aware, margin in designs_of(model, delay_ms, targets):
        t0 = time.perf_counter()
        held, repro = solver_latch(plant, aware, margin)
        sl, change, lqg_cost, closure, log = statistical_linearisation(plant, aware, held, iters, rule, relax, margin)
        print(f"  {model} {delay_ms:g} ms target {label}: latch {int(jnp.sum(held))} commands, repro {float(repro):.2g}; "
              f"per iteration (change, SL LQG cost, "
              f"closure): " + "; ".join(f"{c:.3g}, {q:.3g}, {p:.3g}" for c, q, p in log)
              + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
        stats = {}
        for name, policy in (("det", det), ("aware", aware), ("sl", sl)):
            cost, stats[name] = monte_carlo(plant, policy, trials)
            pooled.setdefault((model, delay_ms, name), []).append(cost)
            if seeds:
                means = [monte_carlo(plant, policy, trials, seed)[1].mean for seed in seeds]
                print(f"  {name}: MC mean under seeds {seeds}: " + " ".join(f"{m:.3g}" for m in means)
                      + f" (their mean {np.mean(means):.3g})", flush=True)
        s = stats["sl"]
        yield (f"| {delay_ms:g} ms | {model} {label} | {cell(stats['det'])} | {cell(stats['aware'])} | {cell(s)} | "
               f"{stats['det'].median:.3g} / {stats['aware'].median:.3g} / {s.median:.3g} | "
               f"{lqg_cost / s.mean:.3g} / {closure / s.mean:.3g} | {change:.2g} |")


def parse_cases(text):
    """'muscle:50:8,arm2:100,muscle:50:all' -> [(model, delay_ms, targets)], one muscle case per delay."""
    cases = {}
    for item in text.split(","):
        model, delay, *target = item.split(":")
        targets = list(range(1, 9)) if target == ["all"] else [int(t) for t in target]
        cases.setdefault((model, float(delay)), []).extend(targets)
    return [(model, delay, targets) for (model, delay), targets in cases.items()]


def main(argv):
    di.configure_cpu()
    cases, trials, iters, rule, relax = parse_cases(argv[1]), int(argv[2]), int(argv[3]), argv[4], float(argv[5])
    seeds = [int(seed) for seed in argv[6].split(",")] if len(argv) > 6 else []
    rows, pooled = [], {}
    for model, delay_ms, targets in cases:
        rows += list(run_case(model, delay_ms, targets, trials, iters, rule, relax, pooled, seeds))
    print(f"\n{trials} trials, seed 0; {iters} SL iterations, rule {rule}, relax {relax}\n")
    print("| delay | case | MC mean det [95 % CI] | noise-aware | SL | median det / noise-aware / SL | "
          "SL predicted / MC: LQG / closure | SL gain change |")
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    for (model, delay_ms, name), costs in pooled.items():
        if len(costs) == 8:
            print(f"pooled over 8 targets, {model} {delay_ms:g} ms, {name}: mean {np.mean(np.concatenate(costs)):.3g}")


if __name__ == "__main__":
    main(sys.argv)
