"""A diagnostic of the six-muscle arm's endpoint ellipses (docs/results/center_out_human.md,
"Noise common to the muscles"): the human preset plus a motor noise common to all muscles.

The extra noise column scales the whole command's departure from the tonic rest by one white
noise, F[4 + i, p] = sigma_c (ud_i - u_rest_i) / t(ud_i, a_i): a gain noise of the descending
command, correlated across the muscles (the preset's own excitation noise is independent per
muscle). Not a default: a measurement of what such a noise would do to the 8 classic reaches
(noise-aware design and Monte Carlo, as in tests/human_reaches.py).

    PYTHONPATH=src .venv/bin/python benchmarks/studies/center_out_common_noise.py --sigma-c 0.02 0.05 [--trials 100]
"""
import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS, _solve  # noqa: E402
from delayed_ilqr.experiments.engine import take  # noqa: E402
from delayed_ilqr.models import muscle  # noqa: E402
from delayed_ilqr.models.arm2_muscle6 import arm2_muscle6, center_out_targets, rest_activations  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from human_reaches import _measure, markdown  # noqa: E402  (a test helper, not in the package)


@dataclass(frozen=True)
class CommonNoise:
    """F(x, u, ud) [10, p + 1]: the preset's noise F and one column sigma_c (ud - rest) / t(ud, a)."""

    F: object
    rest: tuple
    sigma_c: float

    def __call__(self, x, u, ud):
        column = self.sigma_c * (ud - jnp.asarray(self.rest, ud.dtype)) / muscle.activation_time_constant(ud, x[4:])
        return jnp.concatenate([self.F(x, u, ud), jnp.concatenate([jnp.zeros(4, x.dtype), column])[:, None]], axis=1)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sigma-c", type=float, nargs="+", default=[0.02, 0.05])
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    targets = center_out_targets(8, 0.1)
    rest = rest_activations()
    for sigma_c in args.sigma_c:
        plants = [arm2_muscle6(target=tuple(t)) for t in targets]
        plants = [p.replace(noise=CommonNoise(p.noise, rest, sigma_c)) for p in plants]
        solutions = _solve("noise-aware", plants, DEFAULT_OPTIONS).solution
        reaches = [_measure(p, take(solutions, j), args.trials, args.seed + j) for j, p in enumerate(plants)]
        print(f"\n### sigma_c = {sigma_c} ({args.trials} trials per target, seed {args.seed})\n")
        print(markdown(reaches))
        print(f"\nellipse within 30 deg of the movement: {sum(r.angle <= 30 for r in reaches)} of 8; endpoint SD major "
              f"{1e3 * min(r.sd_major for r in reaches):.1f}-{1e3 * max(r.sd_major for r in reaches):.1f} mm; "
              f"major axes from +x {np.min([r.orientation for r in reaches]):.0f}-"
              f"{np.max([r.orientation for r in reaches]):.0f} deg")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
