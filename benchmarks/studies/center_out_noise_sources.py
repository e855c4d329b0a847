"""Where the endpoint scatter of the six-muscle arm's human preset comes from
(docs/results/center_out_human.md, "The noise sources").

The 8 classic 10 cm reaches are designed once with the defaults (``arm2_muscle6(target=...)``:
the noise-aware design and its delayed Kalman filter). Each policy then runs on plants that keep
one noise source and silence the others; the design, the filter and the trial seeds stay the same,
so each source's own endpoint covariance is measured, and their sum can be compared with the
covariance of the full plant (a sum near the full one: the sources add, to first order).

- sources: the signal-dependent excitation noise (sigma_u), the joint-torque noise (sigma_tau), the
  proprioceptive noise (the sensors' G); a silenced sensor keeps G * 1e-6 (G G' must stay positive
  definite).
- windows: the motor noise (both kinds) acting only during [t0, t1) of the reach, the sensors
  quiet: which part of the movement leaves the errors that remain at the end.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/center_out_noise_sources.py [--trials 200] [--seed 0]
"""
import argparse
import dataclasses
import math
import time
from dataclasses import dataclass

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from delayed_ilqr import Observation  # noqa: E402
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS, _solve  # noqa: E402
from delayed_ilqr.experiments.engine import monte_carlo, take  # noqa: E402
from delayed_ilqr.models.arm2_muscle6 import arm2_muscle6, center_out_targets  # noqa: E402
from delayed_ilqr.models.metadata import task_position  # noqa: E402

QUIET = 1e-6                                              # the factor on a silenced sensor's G
SOURCES = {"all": (1.0, 1.0, 1.0), "signal-dependent (sigma_u)": (1.0, 0.0, QUIET),
           "joint torque (sigma_tau)": (0.0, 1.0, QUIET), "proprioceptive": (0.0, 0.0, 1.0)}
WINDOWS = ((0.0, 0.15), (0.15, 0.3), (0.3, 0.4), (0.4, 0.5))


@dataclass(frozen=True)
class _Timed:
    """f(x, u, ud, t) = f(x, u, ud): the arm's dynamics in a time-dependent problem."""

    f: object

    def __call__(self, x, u, ud, t):
        return self.f(x, u, ud)


@dataclass(frozen=True)
class _Window:
    """F(x, u, ud, t): the arm's motor noise during [t0, t1), zero elsewhere."""

    F: object
    t0: float
    t1: float

    def __call__(self, x, u, ud, t):
        return self.F(x, u, ud) * jnp.where((t >= self.t0) & (t < self.t1), 1.0, 0.0)


def _sensors(plant, scale: float):
    o = plant.observation
    return Observation(o.H, o.G * scale, o.delay_steps, o.period)


def with_sources(plant, motor: float, torque: float, sensory: float):
    """The plant with its excitation noise, joint-torque noise and sensory noise scaled."""
    noise = dataclasses.replace(plant.noise, sigma_u=plant.noise.sigma_u * motor,
                                sigma_tau=plant.noise.sigma_tau * torque)
    return plant.replace(noise=noise, observation=_sensors(plant, sensory))


def in_window(plant, t0: float, t1: float):
    """The plant with its motor noise only during [t0, t1) and the sensors quiet."""
    return plant.replace(dynamics=_Timed(plant.dynamics), noise=_Window(plant.noise, t0, t1),
                         time_dependent=True, observation=_sensors(plant, QUIET))


def ellipse(endpoints, direction: float):
    """(covariance [2, 2], SD major, SD minor, major axis vs the movement in [0, 90], from +x in [0, 180))."""
    cov = np.cov(endpoints, rowvar=False)
    values, vectors = np.linalg.eigh(cov)
    axis = math.atan2(vectors[1, -1], vectors[0, -1])
    angle = math.degrees(math.acos(min(1.0, abs(math.cos(axis - direction)))))
    return cov, math.sqrt(values[-1]), math.sqrt(values[0]), angle, math.degrees(axis) % 180.0


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    start = time.perf_counter()
    targets = center_out_targets(8, 0.1)
    plants = [arm2_muscle6(target=tuple(t)) for t in targets]
    solutions = _solve("noise-aware", plants, DEFAULT_OPTIONS).solution
    by_source, by_window = [], []
    for j, plant in enumerate(plants):
        policy = take(solutions, j).policy
        chord = targets[j] - np.asarray(task_position(plant, plant.x0[None]))[0]
        direction = math.atan2(chord[1], chord[0])

        def run(p):
            return ellipse(monte_carlo(p, policy, args.trials, args.seed + j).endpoints, direction)

        sources = {name: run(with_sources(plant, *scales)) for name, scales in SOURCES.items()}
        full = np.trace(sources["all"][0])
        parts = sum(np.trace(s[0]) for name, s in sources.items() if name != "all")
        by_source.append((math.degrees(direction), sources, full, parts))
        by_window.append((math.degrees(direction), [run(in_window(plant, *w)) for w in WINDOWS]))
    print(f"\n### The noise sources ({args.trials} trials per target and source, seed {args.seed}; "
          f"{time.perf_counter() - start:.0f} s)\n")
    print("each cell: endpoint SD major / minor [mm], major axis vs the movement [deg], from +x [deg], share of the "
          "full plant's variance (trace)\n")
    print("| direction [deg] | " + " | ".join(SOURCES) + " | sum of the three / full |")
    print("|---|" + "---|" * (len(SOURCES) + 1))
    for direction, sources, full, parts in by_source:
        cells = [f"{1e3 * s[1]:.1f} / {1e3 * s[2]:.1f}, {s[3]:.0f}, {s[4]:.0f}, {100 * np.trace(s[0]) / full:.0f} %"
                 for s in sources.values()]
        print(f"| {direction:.0f} | " + " | ".join(cells) + f" | {parts / full:.2f} |")
    print("\n### The motor noise by time window (sensors quiet)\n")
    print("each cell: endpoint SD major / minor [mm], major axis vs the movement [deg], from +x [deg]\n")
    print("| direction [deg] | " + " | ".join(f"{t0:.2f}-{t1:.2f} s" for t0, t1 in WINDOWS) + " |")
    print("|---|" + "---|" * len(WINDOWS))
    for direction, windows in by_window:
        cells = [f"{1e3 * w[1]:.1f} / {1e3 * w[2]:.1f}, {w[3]:.0f}, {w[4]:.0f}" for w in windows]
        print(f"| {direction:.0f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
