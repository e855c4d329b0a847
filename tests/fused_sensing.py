"""An independent reference for several delayed sensors, each with its own delay and period: the
Kalman filter on the augmented state Z_k = [dx_k, ..., dx_{k-L}, du_{k-l}, ..., du_{k-1}] (L the
largest delay), on which every sensor is an ordinary undelayed measurement of one block, present at
its sampling steps. Written densely in numpy; nothing here calls the library's recursions."""
from __future__ import annotations

import numpy as np
from delayed_sensing import Augmented, random_problem

from delayed_ilqr.lqg import DelayedObservation


def random_sensors(seed, K, n, specs):
    """One random DelayedObservation per (m, q, delay, period) in ``specs``."""
    rng = np.random.default_rng(seed + 1)
    sensors = []
    for m, q, ls, period in specs:
        G = 0.3 * rng.standard_normal((K, m, q))
        G[:, :, :m] += 0.2 * np.eye(m)
        sensors.append(DelayedObservation(H=rng.standard_normal((K, m, n)), G=G, delay_steps=ls, period=period))
    return sensors


def random_fusion_problem(seed, K, n, d, p, l, specs, *, mult_noise=0.0):
    lqg, _ = random_problem(seed, K, n, d, 1, 1, p, l, 0, mult_noise=mult_noise)
    return lqg, random_sensors(seed, K, n, specs)


class AugmentedSensors(Augmented):
    """``Augmented`` with the history as long as the largest delay and one row block per sensor:
    sensor a's rows measure block l_a of Z at the steps k >= l_a with (k - l_a) % m_a == 0 (zero
    rows, and so zero gain columns, elsewhere)."""

    def __init__(self, lqg, sensors):
        L = max(s.delay_steps for s in sensors)
        K, n = lqg.horizon, lqg.n_states
        super().__init__(lqg, DelayedObservation(np.zeros((K, 1, n)), np.ones((K, 1, 1)), L))
        M = sum(s.n_outputs for s in sensors)
        self.Hz, self.R = np.zeros((K, M, self.N)), np.zeros((K, M, M))
        r = 0
        for s in sensors:
            m, ls = s.n_outputs, s.delay_steps
            self.R[:, r:r + m, r:r + m] = np.asarray(s.measurement_cov)
            for k in range(ls, K):
                if (k - ls) % s.period[0] == 0:
                    self.Hz[k, r:r + m, ls * n:(ls + 1) * n] = np.asarray(s.H)[k]
            r += m
        self.H = np.zeros((K, M, n))

    def kalman(self):
        """As ``Augmented.kalman``, with an update at every step (absent rows have zero H)."""
        K, N, M = self.K, self.N, self.Hz.shape[1]
        P = np.zeros((N, N))
        Lz, posts = np.zeros((K, N, M)), np.zeros((K, N, N))
        for k in range(K):
            S = self.Hz[k] @ P @ self.Hz[k].T + self.R[k]
            Lz[k] = np.linalg.solve(S, self.Hz[k] @ P).T
            P = P - Lz[k] @ S @ Lz[k].T
            posts[k] = P
            P = self.Az[k] @ P @ self.Az[k].T + self.Qz[k]
        return Lz, posts, P

    def loop_kalman_cost(self, Kh):
        """Exact E[cost] of du_k = Kh_k [Z_hat_k; 1] on the augmented Kalman filter designed, step by
        step, for the motor noise E[w_k w_k'] of this very loop (signal-dependent noise included):
        the second moment of xi = [Z; Z_hat; 1] and the filter's covariance advance together.
        Returns (cost, the filter's Cov(dx_k | I_k) [K, n, n])."""
        N, d, n, a = self.N, self.d, self.n, self.a
        X = np.zeros((2 * N + 1, 2 * N + 1))
        X[-1, -1] = 1.0
        P = np.zeros((N, N))
        total, current = 0.0, []
        Z, Zh = slice(0, N), slice(N, 2 * N)
        for k in range(self.K):
            S = self.Hz[k] @ P @ self.Hz[k].T + self.R[k]
            Lz = np.linalg.solve(S, self.Hz[k] @ P).T
            P = P - Lz @ S @ Lz.T
            current.append(P[:n, :n])
            U = np.eye(2 * N + 1)
            U[Zh, Z] += Lz @ self.Hz[k]
            U[Zh, Zh] -= Lz @ self.Hz[k]
            V = np.zeros((2 * N + 1, self.R.shape[1]))
            V[Zh] = Lz
            X = U @ X @ U.T + V @ self.R[k] @ V.T
            stage, X, noise = self._advance(a, k, X, Kh, Z, Zh, n, N, d)
            total += stage
            Qz = np.zeros((N, N))
            Qz[:n, :n] = noise
            P = self.Az[k] @ P @ self.Az[k].T + Qz
        Tc = np.zeros((N + 1, 2 * N + 1))
        Tc[:N, Z], Tc[N, -1] = np.eye(N), 1.0
        return total + np.sum(self._stage_weight(self.K)[:N + 1, :N + 1] * (Tc @ X @ Tc.T)), np.array(current)
