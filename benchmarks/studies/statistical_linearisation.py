"""Feedback gains re-designed by statistical linearisation (SL) of the plant around the
closed loop's predicted distribution, instead of around the nominal
(``docs/results/noise_calibration.md`` §5.3 and §5.5).

The method is the library's ``delayed_ilqr.statistical.statistical_feedback`` (its docstring
has it in full, eq. SL1-SL2): keep the nominal, average the Euler step's Jacobians over the closed
loop's predicted distribution (``prediction.closed_loop_prediction(...).z``, Gaussian closure,
the rule's sigma points), re-solve the gains of that LQG with the solver's backward pass and gain
rule, relax, repeat; "change" is SL2's relative feedback change of the last iteration.

ITERS such iterations start from the noise-aware solver solution. Each of the deterministic
design (``experiments.designs``' "deterministic": the plant without its noise, run in the noise),
the noise-aware design and the SL policy is run ``TRIALS`` times on the plant
(``simulate``, seed 0, the feedforward not applied). SL's own predictions of its cost: the exact
expected cost of its gains on its LQG (``lqg.policy_cost``, feedforward 0) and the Gaussian
closure's (``closed_loop_prediction``, ``rule``).

The solver's feedback latch (commands held without feedback, derivation §12), recovered by
``statistical.solver_latch`` and held in every SL pass: "latch", its size; "repro", the relative
difference of the nominal LQG's pass with it from the solver's feedback, checks the recovery.

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

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr import Options  # noqa: E402
from delayed_ilqr.experiments import designs  # noqa: E402
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS  # noqa: E402
from delayed_ilqr.experiments.engine import solve_batch, take  # noqa: E402
from delayed_ilqr.models import arm2  # noqa: E402
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN  # noqa: E402
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, arm2_muscle6, center_out_targets  # noqa: E402
from delayed_ilqr.statistical import statistical_feedback  # noqa: E402
from delayed_ilqr.statistics import divergence_bound, diverged_trials, sample_stats  # noqa: E402


def designs_of(model: str, delay_ms: float, targets):
    """[(label, plant, deterministic policy, noise-aware policy, design options)] for the targets."""
    delay = delay_ms / 1e3
    if model == "arm2":
        plant = arm2(delay=delay, noise=True, sigma_u=SIGMA_U_HUMAN)
        det_problem, options = designs.design(plant, "deterministic", Options())
        return [("-", plant, di.solve(det_problem).policy, di.solve(plant).policy, options)]
    points = center_out_targets(8, 0.1)
    plants = [arm2_muscle6(**LI_TODOROV, delay=delay, target=tuple(points[j - 1])) for j in targets]
    policies = {}
    for name in ("deterministic", "noise-aware"):
        problems = [designs.design(p, name, DEFAULT_OPTIONS)[0] for p in plants]
        sols = solve_batch(problems, DEFAULT_OPTIONS)
        policies[name] = [take(sols.policy, i) for i in range(len(plants))]
        statuses = [di.Status(int(s)).name for s in np.asarray(sols.status)]
        print(f"  {name} design at {delay_ms:g} ms: {statuses}", flush=True)
    return [(str(j), plant, policies["deterministic"][i], policies["noise-aware"][i], DEFAULT_OPTIONS)
            for i, (j, plant) in enumerate(zip(targets, plants))]


def monte_carlo(plant, policy, trials, seed=0):
    cost = np.asarray(di.simulate(plant, policy, trials, seed=seed).cost)
    return cost, sample_stats(cost, diverged_trials(cost, divergence_bound(plant)))


def cell(stats):
    low, high = stats.ci95
    div = f", {stats.n_diverged} div." if stats.n_diverged else ""
    return f"{stats.mean:.3g} [{low:.3g}, {high:.3g}{div}]"


def run_case(model, delay_ms, targets, trials, iters, rule, relax, pooled, seeds):
    for label, plant, det, aware, options in designs_of(model, delay_ms, targets):
        t0 = time.perf_counter()
        result = statistical_feedback(plant, aware, options, rule=rule, iterations=iters, relax=relax)
        sl, change, lqg_cost, closure = result.policy, float(result.change), float(result.model_cost), \
            float(result.predicted_cost)
        log = zip(np.asarray(result.changes), np.asarray(result.model_costs), np.asarray(result.predicted_costs))
        print(f"  {model} {delay_ms:g} ms target {label}: latch {int(jnp.sum(result.latch))} commands, "
              f"repro {float(result.latch_error):.2g}; per iteration (change, SL LQG cost, "
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
