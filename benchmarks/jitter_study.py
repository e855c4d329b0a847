"""What designing for a jittered input delay gains over designing for the mean delay or the
longest delay (docs/derivation.md §21, docs/results/jitter.md).

Per case (a model and a delay distribution p, the delay drawn at every step independently), three
policies are designed: for the jitter (``Problem(delay_jitter=...)``), for the fixed mean delay
(rounded to a step) and for the fixed longest delay. Each runs on the same jittered plant with the
same trials (one seed: the same motor noise and the same drawn delays for every policy; common
random numbers), and, as the price of robustness, on the plant whose delay is the fixed mean.
Printed: the expected cost of the jitter design (the linearised prediction), the Monte Carlo mean
cost with its 95 % interval, the median with its interval, the trials that diverged, and the
paired difference of each fixed-delay design from the jitter design (mean, 95 % interval, over the
trials finite under both).

Then, for some cases, the same packet delays on a plant that holds the latest arrived command (the
other semantics of derivation §21): the designs for the independent model (with p, and with the
stationary distribution of the acting command's age) and for the fixed mean delay or mean age.

Run: .venv/bin/python benchmarks/jitter_study.py [--trials N] [--seed S] [--cases arm-narrow,arm-wide,cart-pole]
     [--latest arm-narrow,arm-wide,cart-pole]
"""
import argparse
import time

import jax
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.models import arm2, cart_pole
from delayed_ilqr.statistics import divergence_bound, summarize

# (model, distribution): the distributions are chosen, not measured: a 50 ms (arm) or 80 ms
# (cart-pole) mean latency at dt = 10 / 20 ms jittering by one step or by three.
CASES = {
    "arm-narrow": (lambda: arm2(noise=True), di.DelayJitter([4, 5, 6], [0.25, 0.5, 0.25])),
    "arm-wide": (lambda: arm2(noise=True), di.DelayJitter([2, 3, 4, 5, 6, 7, 8],
                                                          [0.05, 0.1, 0.2, 0.3, 0.2, 0.1, 0.05])),
    "cart-pole": (lambda: cart_pole(noise=True), di.DelayJitter([2, 3, 4, 5, 6], [0.1, 0.2, 0.4, 0.2, 0.1])),
}


def paired(a, b, bound):
    """Mean of a - b and its 95 % interval (normal), over the trials that diverged under neither
    (cost finite and below ``bound``)."""
    ok = np.isfinite(a) & np.isfinite(b) & (a <= bound) & (b <= bound)
    d = a[ok] - b[ok]
    half = 1.96 * d.std(ddof=1) / np.sqrt(d.size)
    return d.mean(), d.mean() - half, d.mean() + half


def study(name, trials, seed):
    make, jitter = CASES[name]
    base = make()
    plant = base.replace(delay_steps=jitter.longest, delay_jitter=jitter)
    mean_delay = int(round(jitter.mean))
    fixed_plant = base.replace(delay_steps=mean_delay)
    print(f"\n## {name}: {base.name}, dt = {base.dt:g} s, delays {list(jitter.steps)} steps with p = "
          f"{list(jitter.probabilities)} (mean {jitter.mean:.2f} steps = {1e3 * jitter.mean * base.dt:.0f} ms), "
          f"{trials} trials, seed {seed}\n")
    start = time.perf_counter()
    solutions = {"jitter": di.solve(plant), f"mean delay ({mean_delay})": di.solve(fixed_plant),
                 f"longest delay ({jitter.longest})": di.solve(base.replace(delay_steps=jitter.longest))}
    solve_time = time.perf_counter() - start
    costs = {label: np.asarray(di.simulate(plant, sol.policy, trials, seed=seed).cost)
             for label, sol in solutions.items()}
    bound = divergence_bound(base)
    print("| design | status | expected cost (linearised) | MC mean [95 % CI] | MC median [95 % CI] | diverged "
          "| minus jitter design [95 % CI] | nominal alone (no feedback) | MC mean, plant at the fixed mean delay |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, sol in solutions.items():
        s = summarize(costs[label], np.zeros((trials, 1)), bound)
        fixed = summarize(np.asarray(di.simulate(fixed_plant, sol.policy, trials, seed=seed).cost),
                          np.zeros((trials, 1)), bound)
        open_loop = sol.policy._replace(state_feedback=0 * sol.policy.state_feedback,
                                        delay_feedback=0 * sol.policy.delay_feedback)
        alone = summarize(np.asarray(di.simulate(plant, open_loop, trials, seed=seed).cost), np.zeros((trials, 1)),
                          bound)
        if label == "jitter":
            diff = "-"
        else:
            d, lo, hi = paired(costs[label], costs["jitter"], bound)
            diff = f"{d:.4g} [{lo:.4g}, {hi:.4g}]"
        expected = f"{float(sol.expected_cost):.4g}"
        print(f"| {label} | {sol.status} | {expected} | {s.mean_cost:.4g} [{s.ci95[0]:.4g}, {s.ci95[1]:.4g}] "
              f"| {s.median_cost:.4g} [{s.median_ci95[0]:.4g}, {s.median_ci95[1]:.4g}] | {s.n_diverged} | {diff} "
              f"| {alone.mean_cost:.4g} ({alone.n_diverged} diverged) "
              f"| {fixed.mean_cost:.4g} [{fixed.ci95[0]:.4g}, {fixed.ci95[1]:.4g}] ({fixed.n_diverged} diverged) |")
    print(f"\n(a trial diverged: cost above {bound:.4g}, 100 times the cost of not moving; three solves, "
          f"compilation included: {solve_time:.0f} s)")


class LatestArrived(di.DelayJitter):
    """A measuring device, not a model the solver designs for: the same packet delays, but the
    plant holds the latest arrived command (derivation §21). ``sample`` draws each command's own
    delay tau_j from p and returns the age of the command acting at each step, the smallest i with
    tau_{k-i} <= i (commands before t = 0, zero, count as arrived), so that ``simulate`` runs this
    plant unchanged."""

    def sample(self, key, shape=()):
        import jax.numpy as jnp
        (K,) = shape
        tau = super().sample(key, (K,))
        i = jnp.arange(self.longest + 1)
        sent = jnp.arange(K)[:, None] - i[None, :]                          # [K, L+1] index k - i
        arrived = (sent < 0) | (tau[jnp.clip(sent, 0, K - 1)] <= i[None, :])
        return jnp.argmax(arrived, axis=1).astype(jnp.int32)                 # the first i that arrived

    def __eq__(self, other):
        return type(other) is LatestArrived and super().__eq__(other)

    def __hash__(self):
        return hash(("latest", super().__hash__()))


def ages(jitter, K=200_000):
    """The stationary distribution of the acting command's age under LatestArrived(jitter)."""
    latest = LatestArrived(jitter.steps, jitter.probabilities)
    drawn = np.asarray(latest.sample(jax.random.PRNGKey(1), (K,)))[jitter.longest:]
    steps = sorted(set(drawn.tolist()))
    return di.DelayJitter(steps, [float(np.mean(drawn == s)) for s in steps])


def latest_arrived(name, trials, seed):
    """The designs on a plant that holds the latest arrived command (packet delays p)."""
    make, jitter = CASES[name]
    base = make()
    latest = LatestArrived(jitter.steps, jitter.probabilities)
    age = ages(jitter)
    plant = base.replace(delay_steps=jitter.longest, delay_jitter=latest)
    print(f"\n## {name}, the plant holds the latest arrived command: packet delays p as above; the acting "
          f"command's age is then {list(age.steps)} with frequencies {[round(q, 3) for q in age.probabilities]} "
          f"(mean {age.mean:.2f} steps)\n")
    mean_delay = int(round(jitter.mean))
    designs = {"jitter (independent model, packet delays p)": base.replace(delay_steps=jitter.longest,
                                                                           delay_jitter=jitter),
               "jitter (independent model, the ages' distribution)": base.replace(delay_steps=age.longest,
                                                                                  delay_jitter=age),
               f"mean delay ({mean_delay})": base.replace(delay_steps=mean_delay),
               f"mean age ({int(round(age.mean))})": base.replace(delay_steps=int(round(age.mean)))}
    bound = divergence_bound(base)
    print("| design | MC mean [95 % CI] | MC median [95 % CI] | diverged |")
    print("|---|---|---|---|")
    for label, problem in designs.items():
        policy = di.solve(problem).policy
        s = summarize(np.asarray(di.simulate(plant, policy, trials, seed=seed).cost), np.zeros((trials, 1)), bound)
        print(f"| {label} | {s.mean_cost:.4g} [{s.ci95[0]:.4g}, {s.ci95[1]:.4g}] "
              f"| {s.median_cost:.4g} [{s.median_ci95[0]:.4g}, {s.median_ci95[1]:.4g}] | {s.n_diverged} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--latest", default="",
                        help="cases also run on a plant that holds the latest arrived command")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    for name in args.cases.split(","):
        if name:
            study(name, args.trials, args.seed)
    for name in args.latest.split(","):
        if name:
            latest_arrived(name, args.trials, args.seed)


if __name__ == "__main__":
    main()
