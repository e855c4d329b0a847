"""The delayed Kalman filter (``lqg.delayed_kalman``: gains and covariances, no augmentation) against
the Kalman filter on the augmented state [dx_k, ..., dx_{k-l_s}] (dense, the textbook recursion),
on a P4-sized random time-varying problem (K = 600, n = 4, d = 2, m = 4): median wall time after
compilation, and the largest relative difference of the gains.

Run: .venv/bin/python benchmarks/delayed_filter.py [l_s ...]   (default 10 50 100)
"""
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

import delayed_ilqr as di
from delayed_ilqr import lqg

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from delayed_sensing import random_problem  # noqa: E402  (a test helper, not in the package)
from timing import median_time  # noqa: E402


@jax.jit
def augmented_kalman(A, Q, H, R, P0):
    """Dense Kalman filter on Z = [dx_k, ..., dx_{k-l_s}] (P0 sets the size); returns the gains."""
    n, N = A.shape[1], P0.shape[0]
    ls = N // n - 1

    def step(P, data):
        k, Ak, Qk, Hk, Rk = data
        Hz = jnp.zeros((Hk.shape[0], N)).at[:, ls * n:].set(Hk)
        S = Hz @ P @ Hz.T + Rk
        gain = jnp.where(k >= ls, jnp.linalg.solve(S, Hz @ P).T, 0.0)
        P = P - gain @ S @ gain.T
        Az = jnp.zeros((N, N)).at[:n, :n].set(Ak).at[n:, :N - n].set(jnp.eye(N - n))
        P = Az @ P @ Az.T + jnp.zeros((N, N)).at[:n, :n].set(Qk)
        return 0.5 * (P + P.T), gain

    _, gains = jax.lax.scan(step, P0, (jnp.arange(A.shape[0]), A, Q, H, R))
    return gains


def main():
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    delays = [int(a) for a in sys.argv[1:]] or [10, 50, 100]
    K, n, d, m = 600, 4, 2, 4
    print(f"{'l_s':>4} {'n (l_s+1)':>9} {'delayed filter':>15} {'augmented filter':>17} {'ratio':>7} "
          f"{'max rel. diff':>14}")
    for ls in delays:
        model, obs = random_problem(0, K, n, d, m, m, 2, 5, ls)
        Q = jnp.einsum("kpn,kpm->knm", model.c, model.c)
        P0 = jnp.zeros((n * (ls + 1),) * 2)
        t_delayed = median_time(lambda: lqg.delayed_kalman(model, obs), repeats=7)
        t_aug = median_time(lambda: augmented_kalman(model.A, Q, obs.H, obs.measurement_cov, P0), repeats=3)
        fg, _ = lqg.delayed_kalman(model, obs)
        gains = augmented_kalman(model.A, Q, obs.H, obs.measurement_cov, P0)
        diff = max(float(jnp.max(jnp.abs(fg.delayed_gain - gains[:, ls * n:])) / jnp.max(jnp.abs(gains[:, ls * n:]))),
                   float(jnp.max(jnp.abs(fg.current_gain - gains[:, :n])) / jnp.max(jnp.abs(gains[:, :n]))))
        print(f"{ls:4d} {n * (ls + 1):9d} {t_delayed * 1e3:12.2f} ms {t_aug * 1e3:14.2f} ms {t_aug / t_delayed:7.0f} "
              f"{diff:14.2e}", flush=True)


if __name__ == "__main__":
    main()
