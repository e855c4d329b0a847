"""A diagnostic of the six-muscle arm's endpoint ellipses (docs/results/center_out_human.md,
"Noise common to the muscles"): the human preset plus a motor noise common to all muscles.

Two kinds of common noise, each one extra column of F (the preset's own excitation noise is
independent per muscle):

- ``--sigma-c``: a gain noise of the descending command, one white noise scaling the whole
  command's departure from the tonic rest, F[4 + i, p] = sigma_c (ud_i - u_rest_i) / t(ud_i, a_i);
- ``--sigma-t``: a temporal noise of the commands (van Beers, Haggard & Wolpert 2004's noise in
  their duration), the activations advancing on a jittered clock, da = (ud - a) / t(ud, a)
  (dt + sigma_t dw): F[4 + i, p] = sigma_t (ud_i - a_i) / t(ud_i, a_i), sigma_t in s^1/2.

Not defaults: measurements of what such noises do to the 8 classic reaches (noise-aware design
and Monte Carlo, as in tests/human_reaches.py); ``--position-sense`` runs them on
``arm2_muscle6(**POSITION_SENSE)``.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/center_out_common_noise.py --sigma-c 0.02 0.05 [--trials 100]
    PYTHONPATH=src .venv/bin/python benchmarks/studies/center_out_common_noise.py --sigma-c 0 --sigma-t 0.01 0.03
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
from delayed_ilqr.models.arm2_muscle6 import (POSITION_SENSE, arm2_muscle6, center_out_targets,  # noqa: E402
                                              rest_activations)

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from human_reaches import _measure, markdown  # noqa: E402  (a test helper, not in the package)


@dataclass(frozen=True)
class CommonNoise:
    """F(x, u, ud) [10, p + 1 or p + 2]: the preset's noise F, the gain column
    sigma_c (ud - rest) / t(ud, a) if sigma_c > 0 and the temporal column sigma_t (ud - a) / t(ud, a)
    if sigma_t > 0."""

    F: object
    rest: tuple
    sigma_c: float
    sigma_t: float = 0.0

    def __call__(self, x, u, ud):
        a = x[4:]
        t = muscle.activation_time_constant(ud, a)
        columns = [self.sigma_c * (ud - jnp.asarray(self.rest, ud.dtype)) / t] if self.sigma_c > 0 else []
        columns += [self.sigma_t * (ud - a) / t] if self.sigma_t > 0 else []
        extra = jnp.concatenate([jnp.zeros((4, len(columns)), x.dtype), jnp.stack(columns, axis=1)], axis=0)
        return jnp.concatenate([self.F(x, u, ud), extra], axis=1)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sigma-c", type=float, nargs="+", default=[0.02, 0.05])
    parser.add_argument("--sigma-t", type=float, nargs="+", default=[0.0])
    parser.add_argument("--position-sense", action="store_true", help="arm2_muscle6(**POSITION_SENSE)")
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    targets = center_out_targets(8, 0.1)
    rest = rest_activations()
    model = POSITION_SENSE if args.position_sense else {}
    for sigma_c in args.sigma_c:
        for sigma_t in args.sigma_t:
            if sigma_c <= 0 and sigma_t <= 0:
                raise SystemExit("each run needs sigma_c > 0 or sigma_t > 0 (the preset alone: center_out_human.py)")
            plants = [arm2_muscle6(target=tuple(t), **model) for t in targets]
            plants = [p.replace(noise=CommonNoise(p.noise, rest, sigma_c, sigma_t)) for p in plants]
            solutions = _solve("noise-aware", plants, DEFAULT_OPTIONS).solution
            reaches = [_measure(p, take(solutions, j), args.trials, args.seed + j) for j, p in enumerate(plants)]
            print(f"\n### sigma_c = {sigma_c}, sigma_t = {sigma_t}{', POSITION_SENSE' if model else ''} "
                  f"({args.trials} trials per target, seed {args.seed})\n")
            print(markdown(reaches))
            print(f"\nellipse within 30 deg of the movement: {sum(r.angle <= 30 for r in reaches)} of 8; endpoint SD "
                  f"major {1e3 * min(r.sd_major for r in reaches):.1f}-{1e3 * max(r.sd_major for r in reaches):.1f} mm; "
                  f"major axes from +x {np.min([r.orientation for r in reaches]):.0f}-"
                  f"{np.max([r.orientation for r in reaches]):.0f} deg")
            sys.stdout.flush()


if __name__ == "__main__":
    main()
