"""Several delayed sensors fused without augmentation (``lqg.fused_kalman``: a base filter at the
largest delay and a re-filter over the window) against the Kalman filter on the augmented state
[dx_k, ..., dx_{k-L}] (dense, the textbook recursion), on a random time-varying problem (K = 300,
n = 4, d = 2): a fast sensor (m = 4, delay L/4, every step) and a slow one (m = 2, delay L, every
third step), as proprioception and vision. Median wall time after compilation (the augmented filter: one run), and the largest
relative difference of the covariances Cov(dx_k | I_k).

Run: PYTHONPATH=src .venv/bin/python benchmarks/fused_filter.py [L ...]   (default 50 200)
"""
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import delayed_ilqr as di
from delayed_ilqr import lqg

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from fused_sensing import random_fusion_problem  # noqa: E402  (a test helper, not in the package)

from timing import median_time  # noqa: E402


def augmented_model(sensors, n):
    """(Hz [K, M, N], R [K, M, M]) of the sensors on Z = [dx_k, ..., dx_{k-L}] (absent rows zero)."""
    K, L = sensors[0].horizon, max(s.delay_steps for s in sensors)
    M = sum(s.n_outputs for s in sensors)
    Hz, R = np.zeros((K, M, n * (L + 1))), np.zeros((K, M, M))
    r = 0
    for s in sensors:
        m, ls = s.n_outputs, s.delay_steps
        present = np.asarray(s.present)[:, 0]
        Hz[:, r:r + m, ls * n:(ls + 1) * n] = np.asarray(s.H) * present[:, None, None]
        R[:, r:r + m, r:r + m] = np.asarray(s.measurement_cov)
        r += m
    return jnp.asarray(Hz), jnp.asarray(R)


@jax.jit
def augmented_kalman(A, Q, Hz, R):
    """Dense Kalman filter on Z; returns Cov(dx_k | I_k) [K, n, n]."""
    n, N = A.shape[1], Hz.shape[2]

    def step(P, data):
        Ak, Qk, Hk, Rk = data
        S = Hk @ P @ Hk.T + Rk
        gain = jnp.linalg.solve(S, Hk @ P).T
        P = P - gain @ S @ gain.T
        current = P[:n, :n]
        Az = jnp.zeros((N, N)).at[:n, :n].set(Ak).at[n:, :N - n].set(jnp.eye(N - n))
        P = Az @ P @ Az.T + jnp.zeros((N, N)).at[:n, :n].set(Qk)
        return 0.5 * (P + P.T), current

    return jax.lax.scan(step, jnp.zeros((N, N)), (A, Q, Hz, R))[1]


def main():
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    delays = [int(a) for a in sys.argv[1:]] or [50, 200]
    K, n, d = 300, 4, 2
    print(f"{'L':>4} {'n (L+1)':>8} {'fused filter':>13} {'augmented filter':>17} {'ratio':>7} {'max rel. diff':>14}")
    for L in delays:
        model, sensors = random_fusion_problem(0, K, n, d, 2, 5, [(4, 4, L // 4, 1), (2, 2, L, 3)])
        Q = jnp.einsum("kpn,kpm->knm", model.c, model.c)
        Hz, R = augmented_model(sensors, n)
        t_fused = median_time(lambda: lqg.fused_kalman(model, sensors), 5)
        _, cov = lqg.fused_kalman(model, sensors)
        compiled = augmented_kalman.lower(model.A, Q, Hz, R).compile()     # one timed run: it is slow
        start = time.perf_counter()
        ref = jax.block_until_ready(compiled(model.A, Q, Hz, R))
        t_aug = time.perf_counter() - start
        diff = float(jnp.max(jnp.abs(cov.current[:-1] - ref)) / jnp.max(jnp.abs(ref)))
        print(f"{L:4d} {n * (L + 1):8d} {t_fused * 1e3:10.1f} ms {t_aug * 1e3:14.1f} ms {t_aug / t_fused:7.0f} "
              f"{diff:14.2e}", flush=True)


if __name__ == "__main__":
    main()
