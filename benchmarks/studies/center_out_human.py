"""The center-out study of the six-muscle arm's human preset (docs/results/center_out_human.md).

The 8 classic 10 cm targets and targets the tests do not use (other distances, directions between
the classic ones), each set solved in one batch with the model's defaults (``arm2_muscle6(target=...)``:
20 ms motor delay, proprioception 40 ms late, signal-dependent and -independent motor noise, tonic
rest), then measured by Monte Carlo (tests/human_reaches.py): prints one markdown table per set.
``--position-sense``: the preset with proprioception at the precision of human position sense
(``arm2_muscle6(**POSITION_SENSE)``), ``--joint-noise-scale S``: both proprioceptive noise densities
S times the preset's; ``--sets``: which sets to run (default all three).

    PYTHONPATH=src .venv/bin/python benchmarks/studies/center_out_human.py [--trials 300] [--seed 0] [--position-sense]
"""
import argparse
import math
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from human_reaches import center_out_reaches, markdown  # noqa: E402  (a test helper, not in the package)
from delayed_ilqr.models.arm2_muscle6 import POSITION_SENSE  # noqa: E402
from delayed_ilqr.models.sensors import JOINT_ANGLE_DENSITY, JOINT_VELOCITY_DENSITY  # noqa: E402

SETS = (("the 8 classic targets, 10 cm", dict(n_targets=8, radius=0.1)),
        ("unseen: 15 cm, directions 22.5 deg off the classic ones", dict(n_targets=8, radius=0.15, start_angle=math.pi / 8)),
        ("unseen: 6 cm, directions 22.5 deg off the classic ones", dict(n_targets=8, radius=0.06, start_angle=math.pi / 8)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--position-sense", action="store_true", help="proprioception of human position sense")
    parser.add_argument("--joint-noise-scale", type=float, help="both proprioceptive noise densities times this")
    parser.add_argument("--sets", type=int, nargs="+", default=list(range(len(SETS))),
                        help="which sets: 0 the classic targets, 1 unseen 15 cm, 2 unseen 6 cm")
    args = parser.parse_args()
    model = POSITION_SENSE if args.position_sense else {}
    if args.joint_noise_scale is not None:
        model = {"joint_angle_noise": args.joint_noise_scale * JOINT_ANGLE_DENSITY,
                 "joint_velocity_noise": args.joint_noise_scale * JOINT_VELOCITY_DENSITY}
    for title, kwargs in (SETS[i] for i in args.sets):
        start = time.perf_counter()
        reaches = center_out_reaches(n_trials=args.trials, seed=args.seed, **kwargs, **model)
        aligned = sum(r.angle <= 30 for r in reaches)
        print(f"\n### {title}{f', proprioception {model}' if model else ''} ({args.trials} trials per target, seed {args.seed}; "
              f"{time.perf_counter() - start:.0f} s)\n")
        print(markdown(reaches))
        print(f"\nellipse within 30 deg of the movement: {aligned} of {len(reaches)}; excitations at a bound "
              f"{100 * min(r.at_bound for r in reaches):.0f}-{100 * max(r.at_bound for r in reaches):.0f} %, zero "
              f"feedback rows {100 * min(r.zero_rows for r in reaches):.0f}-{100 * max(r.zero_rows for r in reaches):.0f} %")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
