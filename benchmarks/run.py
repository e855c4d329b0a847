"""The benchmark suite: prints one report and writes it to ``benchmarks/results.md``.

Run with ``make bench`` (never by CI); it takes several minutes on a 2-core CPU. What it measures:

1. Full solves of P1 to P4 (``docs/models.md`` §2) with both methods of ``delayed_ilqr.solve``,
   structured (Theorem 1) and augmented (Riccati on the augmented state), in the same run. "First
   call" is the first ``solve`` of that problem and method in this process (compilation included);
   "median" is the median of the solves after it (at least 7, more until 0.5 s are spent, 3 when a
   solve takes over 2 s). The reference times of other tools are quoted, not measured; where
   crocoddyl is installed (``make bench`` installs it), its DDP is also timed in this run on P1
   and P4 up to l = 100 (``crocoddyl_ref.py``).
2. The backward pass alone: P4 linearised at u = 0 for l = 10 ... 200, the compiled structured
   pass (``structured_slot_scan(store_value=False, predict=True)``, what the solver runs) against the compiled
   augmented one (``augmented_scan``), and the exponent a of time ~ l^a fitted in log-log.
3. Memory: temp + output + argument bytes of the compiled solver (XLA's ``memory_analysis``)
   against the size of the returned gains, K (d + d n + l d^2) float64 numbers.
4. Compilation: the first call of P2 in a fresh Python process, then a second P2 problem of the
   same shapes (another target) that must reuse the compiled solver.
5. Batches: 64 P2 problems (64 targets) in one ``jax.jit(jax.vmap(solve))`` call, against 64
   separate solves, the two timed alternately.

Every timed call is wrapped in ``jax.block_until_ready``. The machines are shared and noisy, so
only ratios measured within one run are meaningful; absolute times move between runs.
"""
from __future__ import annotations

import datetime
import math
import os
import platform
import statistics
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.ilqg.linearize import linearize, rollout
from delayed_ilqr.lqg.augmented import augmented_scan
from delayed_ilqr.lqg.structured import structured_slot_scan
from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.ilqg.solver import compiled_solver
from timing import first_and_median, timed

RESULTS = Path(__file__).with_name("results.md")
OPTIONS = {"structured": di.Options(), "augmented": di.Options(method="augmented")}
P4_DELAYS = (1, 10, 50, 100, 200)
SCALING_DELAYS = (10, 20, 50, 100, 200)
# best compiled median of other tools (state augmentation, 2-core machine), quoted, not measured
REFERENCE = {("P1", 10): ("crocoddyl", 0.7e-3), ("P2", 10): ("trajax", 8.1e-3),
             ("P3", 50): ("trajax", 0.293), ("P4", 100): ("trajax", 0.79), ("P4", 200): ("trajax", 5.3)}
# solved by crocoddyl's DDP in this run too, when it is installed (P4 l = 200: minutes a solve)
CROCODDYL_ROWS = (("P1", 10), ("P4", 1), ("P4", 10), ("P4", 50), ("P4", 100))
BATCH_REPEATS = 9
P2_TARGET = np.array([math.pi / 2, math.pi / 3, 0.0, 0.0])
FIRST_CALL_SNIPPET = """
import time, jax, delayed_ilqr as di
from delayed_ilqr.models import arm2
jax.config.update("jax_enable_x64", True)
di.configure_cpu()
problem = arm2(delay=0.1)
start = time.perf_counter()
jax.block_until_ready(di.solve(problem))
print(time.perf_counter() - start)
"""


# ---------------------------------------------------------------------------------------------
# timing and formatting
# ---------------------------------------------------------------------------------------------


def fmt_time(seconds: float) -> str:
    if seconds < 1.0:
        return f"{seconds * 1e3:.3g} ms"
    return f"{seconds:.3g} s"


def fmt_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB"):
        if n < 1e3:
            return f"{n:.3g} {unit}"
        n /= 1e3
    return f"{n:.3g} GB"


def table(header, rows) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + \
           ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]


def fitted_exponent(delays, times) -> float:
    """Least-squares slope of log(time) against log(l)."""
    return float(np.polyfit(np.log(delays), np.log(times), 1)[0])


# ---------------------------------------------------------------------------------------------
# 1. full solves
# ---------------------------------------------------------------------------------------------

def benchmark_problems():
    """(name, problem) for P1 l=10, P2 l=10, P3 l=50 and P4 at each of P4_DELAYS."""
    rows = [("P1", point_mass(delay=0.1)), ("P2", arm2(delay=0.1)), ("P3", arm2(delay=0.1, dt=0.002))]
    return rows + [("P4", point_mass(dt=0.001, delay=l * 0.001)) for l in P4_DELAYS]


@dataclass
class Run:
    first_s: float
    median_s: float
    iterations: int
    cost: float
    status: str


def solve_run(problem, method: str) -> Run:
    sol, first, median = first_and_median(lambda: di.solve(problem, options=OPTIONS[method]))
    return Run(first, median, int(sol.iterations), float(sol.cost), di.Status(int(sol.status)).name)


def full_solves(problems):
    """{(name, l): {method: Run}}, both methods of a row measured one after the other."""
    runs = {}
    for name, problem in problems:
        runs[name, problem.delay_steps] = {m: solve_run(problem, m) for m in OPTIONS}
        print(f"  solved {name} l={problem.delay_steps}", file=sys.stderr)
    return runs


def crocoddyl_times():
    """{(name, l): (median s, iterations, cost)} of crocoddyl's DDP on CROCODDYL_ROWS, timed now;
    {} when crocoddyl is not installed."""
    try:
        import crocoddyl_ref
    except ImportError:
        print("  crocoddyl is not installed: its times are only quoted", file=sys.stderr)
        return {}
    cases = [(name, 0.01 if name == "P1" else 0.001, l) for name, l in CROCODDYL_ROWS]
    times = crocoddyl_ref.crocoddyl_solve_times(cases, solvers=("DDP",))
    return {(name, l): value for (name, _, l, _), value in times.items()}


def full_solve_section(problems, runs, croc) -> list[str]:
    rows = []
    for name, p in problems:
        s, a = runs[name, p.delay_steps]["structured"], runs[name, p.delay_steps]["augmented"]
        tool, ref = REFERENCE.get((name, p.delay_steps), ("-", None))
        c = croc.get((name, p.delay_steps))
        rows.append([name, p.horizon, p.delay_steps,
                     fmt_time(s.first_s), fmt_time(s.median_s), s.iterations, f"{s.cost:.8e}",
                     fmt_time(a.first_s), fmt_time(a.median_s), a.iterations, f"{a.cost:.8e}",
                     f"{a.median_s / s.median_s:.1f}", f"{abs(a.cost - s.cost) / abs(s.cost):.1e}",
                     "-" if ref is None else f"{tool} {fmt_time(ref)}",
                     "-" if ref is None else f"{ref / s.median_s:.1f}",
                     "-" if c is None else f"{fmt_time(c[0])} ({c[1]} it)",
                     "-" if c is None else f"{c[0] / s.median_s:.1f}",
                     "-" if c is None else f"{abs(c[2] - s.cost) / abs(s.cost):.1e}"])
    header = ["problem", "K", "l", "structured first call", "structured median", "it", "structured cost",
              "augmented first call", "augmented median", "it", "augmented cost", "aug / struct",
              "cost rel. diff", "reference (quoted)", "ref / ours", "crocoddyl DDP, this run", "croc / ours",
              "croc cost rel. diff"]
    statuses = sorted({r.status for row in runs.values() for r in row.values()})
    return ["## 1. Full solves, both methods, same run", "",
            "First call includes compilation; median of the solves after it (at least 7, more until "
            "0.5 s are spent; 3 when a solve takes over 2 s). \"reference\" is the best compiled median of other tools (state augmentation, "
            "2-core machine) quoted, **not measured here**; \"ref / ours\" divides it by "
            f"the structured median. \"crocoddyl DDP, this run\" is crocoddyl {croc_version()} timed in this "
            "process on the same problem by state augmentation (C++ LQR action models, one thread; "
            "`crocoddyl_ref.py`), \"it\" its steps taken. "
            f"Final statuses: {', '.join(statuses)}.", ""] + table(header, rows)


def croc_version() -> str:
    try:
        import crocoddyl
    except ImportError:
        return "(not installed)"
    return crocoddyl.__version__


# ---------------------------------------------------------------------------------------------
# 2. backward-pass scaling
# ---------------------------------------------------------------------------------------------

def p4_lqg(l: int):
    """P4 linearised at u = 0."""
    problem = point_mass(dt=0.001, delay=l * 0.001)
    us = jnp.zeros((problem.horizon, problem.n_controls))
    return linearize(problem, rollout(problem, us), us)


def backward_pass_times():
    """{l: (structured s, augmented s, |J0 difference| / |J0|)}, compiled medians."""
    # J(0) and the line-search model (a, b): all that the solver's pass computes stays live
    structured = jax.jit(lambda q: (lambda gains, out, ok, model: (out[0][0], *model))(
        *structured_slot_scan(q, 0.0, store_value=False, predict=True)))
    augmented = jax.jit(lambda q: augmented_scan(q, 0.0)[1].s_tilde[0])
    times = {}
    for l in SCALING_DELAYS:
        lqg = p4_lqg(l)
        j_s, _, t_s = first_and_median(lambda: structured(lqg))
        j_a, _, t_a = first_and_median(lambda: augmented(lqg))
        times[l] = (t_s, t_a, abs(float(j_s[0]) - float(j_a)) / abs(float(j_a)))
    return times


def scaling_section(times) -> list[str]:
    rows = [[l, 4 + 2 * l, fmt_time(t_s), fmt_time(t_a), f"{t_a / t_s:.1f}", f"{rel:.1e}"]
            for l, (t_s, t_a, rel) in times.items()]
    a_structured, a_augmented = scaling_exponents(times)
    return ["## 2. Backward-pass scaling (P4 linearised at u = 0, K = 600, n = 4, d = 2)", "",
            "Compiled passes, median of at least 7 runs (more until 0.5 s are spent, 3 over 2 s). Per step the structured pass costs "
            "O(l^2 d^3 + l n^2 d + n^3), the augmented one O((n + l d)^3).", ""] + \
        table(["l", "N = n + l d", "structured", "augmented", "aug / struct", "J(0) rel. diff"], rows) + \
        ["", f"Fitted exponent, time ~ l^a over l = {', '.join(map(str, times))}: "
             f"structured a = {a_structured:.2f}, augmented a = {a_augmented:.2f}."]


def scaling_exponents(times):
    delays = list(times)
    return tuple(fitted_exponent(delays, [times[l][i] for l in delays]) for i in (0, 1))


# ---------------------------------------------------------------------------------------------
# 3. memory
# ---------------------------------------------------------------------------------------------

def compiled_bytes(problem, method: str) -> int:
    """temp + output + argument bytes of the compiled solver (already compiled: a cache hit)."""
    u_init = jnp.zeros((problem.horizon, problem.n_controls))
    stats = compiled_solver(problem).lower(problem, u_init, OPTIONS[method]).compile().memory_analysis()
    return stats.temp_size_in_bytes + stats.output_size_in_bytes + stats.argument_size_in_bytes


def gains_bytes(problem) -> int:
    K, n, d, l = problem.horizon, problem.n_states, problem.n_controls, problem.delay_steps
    return K * (d + d * n + l * d * d) * 8


def memory_ratios(problems):
    """[(name, problem, gains bytes, structured bytes, augmented bytes)]."""
    return [(name, p, gains_bytes(p), compiled_bytes(p, "structured"), compiled_bytes(p, "augmented"))
            for name, p in problems]


def memory_section(memory) -> list[str]:
    rows = [[name, p.delay_steps, fmt_bytes(g), fmt_bytes(s), f"{s / g:.1f}", fmt_bytes(a), f"{a / g:.1f}"]
            for name, p, g, s, a in memory]
    return ["## 3. Memory of the compiled solver", "",
            "XLA's `memory_analysis()` of the compiled `solve`: temp + output + argument bytes (the "
            "output holds the gains, the trajectory and the trace). Gains: K (d + d n + l d^2) float64. "
            "The structured solver stores no LQ model (it linearises inside the backward pass) and no "
            "line-search candidates (scored as they run), so at small l, where the gains are smallest, "
            "what remains is the nominal, the gains and the output; the augmented reference stores its "
            "model.", ""] + \
        table(["problem", "l", "gains", "structured", "struct / gains", "augmented", "aug / gains"], rows)


# ---------------------------------------------------------------------------------------------
# 4. compilation
# ---------------------------------------------------------------------------------------------

def fresh_process_first_call() -> float:
    """Seconds of the first P2 solve in a new Python process (import excluded)."""
    out = subprocess.run([sys.executable, "-c", FIRST_CALL_SNIPPET], check=True, capture_output=True, text=True)
    return float(out.stdout.split()[-1])


def second_problem_first_call():
    """(first-call seconds, compilations added) of P2 with another target, after P2 was solved."""
    other = arm2(delay=0.1, x_target=P2_TARGET + [0.2, -0.1, 0.0, 0.0])
    before = compiled_solver(other)._cache_size()
    _, seconds = timed(lambda: di.solve(other))
    return seconds, compiled_solver(other)._cache_size() - before


def compilation_section(first_fresh, first_in_run, second_s, recompiled) -> list[str]:
    return ["## 4. Compilation (P2, l = 10)", "",
            f"- first call in a fresh process (compilation included): {fmt_time(first_fresh)} "
            f"(first call in this run, after P1: {fmt_time(first_in_run)})",
            f"- a second P2 problem, other target, same shapes: first call {fmt_time(second_s)}, "
            f"new compilations: {recompiled}"]


# ---------------------------------------------------------------------------------------------
# 5. batches
# ---------------------------------------------------------------------------------------------

def p2_batch(size: int = 64):
    """P2 with ``size`` targets on a grid of +-0.2 rad around the P2 target."""
    offsets = np.linspace(-0.2, 0.2, math.isqrt(size))
    return [arm2(delay=0.1, x_target=P2_TARGET + [a, b, 0.0, 0.0]) for a in offsets for b in offsets]


def batch_timings(problems):
    """Batched and separate solves: per-problem seconds, costs and iterations of each."""
    stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *problems)
    batched_solve = jax.jit(jax.vmap(di.solve))
    batch_call, separate_calls = (lambda: batched_solve(stacked)), (lambda: [di.solve(p) for p in problems])
    batched, separate = timed(batch_call)[0], timed(separate_calls)[0]            # compilation
    # alternately, so that the machine's drift moves both medians alike
    times = [(timed(batch_call)[1], timed(separate_calls)[1]) for _ in range(BATCH_REPEATS)]
    t_batch, t_separate = (statistics.median(t) for t in zip(*times))
    return dict(batch_s=t_batch / len(problems), separate_s=t_separate / len(problems),
                batch_cost=np.asarray(batched.cost), separate_cost=np.array([float(s.cost) for s in separate]),
                batch_iterations=np.asarray(batched.iterations),
                separate_iterations=np.array([int(s.iterations) for s in separate]))


def batch_section(b, single_median) -> list[str]:
    rel = np.max(np.abs(b["batch_cost"] - b["separate_cost"]) / np.abs(b["separate_cost"]))
    n = len(b["batch_cost"])
    return [f"## 5. Batches ({n} P2 problems, {n} targets)", "",
            f"- one `jax.jit(jax.vmap(solve))` call: {fmt_time(b['batch_s'])} per problem (median of "
            f"{BATCH_REPEATS} batch calls / {n}, alternating with the loops below)",
            f"- {n} separate solves: {fmt_time(b['separate_s'])} per problem (median of {BATCH_REPEATS} loops / {n}); "
            f"P2 single solve (section 1): {fmt_time(single_median)}",
            f"- batched / separate per problem: {b['batch_s'] / b['separate_s']:.2f}",
            f"- iterations: separate {b['separate_iterations'].min()} to {b['separate_iterations'].max()} "
            f"(mean {b['separate_iterations'].mean():.1f}); batched iterations agree with separate: "
            f"{bool(np.all(b['batch_iterations'] == b['separate_iterations']))}",
            f"- batched cost == separate cost for all {n}: max relative difference {rel:.1e} "
            f"({'ok' if rel <= 1e-9 else 'FAILS'} at 1e-9)"]


# ---------------------------------------------------------------------------------------------
# the performance goals and the report
# ---------------------------------------------------------------------------------------------

def goals_section(runs, exponents, memory, first_fresh, recompiled, batch, croc) -> list[str]:
    s = {key: r["structured"].median_s for key, r in runs.items()}
    p4_aug = runs["P4", 200]["augmented"].median_s
    ratios = {(name, p.delay_steps): st / g for name, p, g, st, _ in memory}
    worst = max(ratios, key=ratios.get)
    goals = [
        ("P4 l=200 vs trajax 5.3 s", ">= 50x", 5.3 / s["P4", 200], 50),
        ("P4 l=200 vs own augmented, same run", ">= 50x", p4_aug / s["P4", 200], 50),
        ("P3 l=50 vs trajax 293 ms", ">= 10x", 0.293 / s["P3", 50], 10),
        ("P1 l=10 vs crocoddyl 0.7 ms", "> 1x", 0.7e-3 / s["P1", 10], 1),
        ("P2 l=10 vs trajax 8.1 ms", "> 1x", 8.1e-3 / s["P2", 10], 1),
    ]
    if ("P1", 10) in croc:
        goals.insert(4, ("P1 l=10 vs crocoddyl DDP timed in this run", "> 1x", croc["P1", 10][0] / s["P1", 10], 1))
    rows = [[goal, target, f"{x:.1f}x", "met" if x >= bound else "**not met**"] for goal, target, x, bound in goals]
    rows += [
        ["P2 first call (fresh process)", "< 3 s", fmt_time(first_fresh), "met" if first_fresh < 3 else "**not met**"],
        ["second P2 problem, same shapes", "no recompilation", f"{recompiled} new",
         "met" if recompiled == 0 else "**not met**"],
        ["structured backward pass vs l", "a <= ~2", f"a = {exponents[0]:.2f}",
         "met" if exponents[0] <= 2.0 else "**not met**"],
        ["structured solver memory / gains, P4 l=200", "a few times (<= 5x here)", f"{ratios['P4', 200]:.1f}x",
         "met" if ratios["P4", 200] <= 5 else "**not met**"],
        ["structured solver memory / gains, worst row", "a few times (<= 5x here)",
         f"{ratios[worst]:.1f}x ({worst[0]} l={worst[1]})", "met" if ratios[worst] <= 5 else "**not met**"],
        ["vmap of 64 P2 solves vs 64 separate", "< 1x per problem", f"{batch['batch_s'] / batch['separate_s']:.2f}x",
         "met" if batch["batch_s"] < batch["separate_s"] else "**not met**"],
    ]
    return ["## Goals", "",
            "Speed-ups use the structured median of section 1; the reference times are quoted, "
            "except the row that says it was timed in this run.",
            ""] + table(["goal", "target", "measured", "status"], rows)


def header() -> list[str]:
    cpu = platform.processor() or platform.machine()
    return ["# delayed_ilqr benchmarks", "",
            f"{datetime.date.today().isoformat()}; {cpu}, {os.cpu_count()} CPUs; JAX {jax.__version__} on "
            f"{jax.default_backend()}, float64. Produced by `make bench` (`benchmarks/run.py`).", "",
            "These 2-core machines are shared and noisy: absolute times move between runs, so every "
            "ratio below is measured within this one run."]


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    problems = benchmark_problems()
    first_fresh = fresh_process_first_call()
    runs = full_solves(problems)
    second_s, recompiled = second_problem_first_call()
    times = backward_pass_times()
    memory = memory_ratios(problems)
    batch = batch_timings(p2_batch())
    croc = crocoddyl_times()
    sections = [
        header(),
        goals_section(runs, scaling_exponents(times), memory, first_fresh, recompiled, batch, croc),
        full_solve_section(problems, runs, croc),
        scaling_section(times),
        memory_section(memory),
        compilation_section(first_fresh, runs["P2", 10]["structured"].first_s, second_s, recompiled),
        batch_section(batch, runs["P2", 10]["structured"].median_s),
    ]
    text = "\n\n".join("\n".join(lines) for lines in sections) + "\n"
    print(text)
    RESULTS.write_text(text)


if __name__ == "__main__":
    main()
