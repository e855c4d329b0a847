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
        total, current, _, _ = self._loop_kalman(Kh)
        return total, current

    def loop_kalman_gains(self, Kh):
        """The augmented Kalman gains [K, N, M] for the motor noise of the loop of ``Kh`` (as in
        ``loop_kalman_cost``), and that noise [K, n, n]."""
        _, _, gains, noises = self._loop_kalman(Kh)
        return gains, noises

    def _loop_kalman(self, Kh):
        """The walk of ``loop_kalman_cost``: (cost, Cov(dx_k | I_k) [K, n, n], the gains [K, N, M],
        the loop's motor noise [K, n, n])."""
        N, d, n, a = self.N, self.d, self.n, self.a
        X = np.zeros((2 * N + 1, 2 * N + 1))
        X[-1, -1] = 1.0
        P = np.zeros((N, N))
        total, current, gains, noises = 0.0, [], [], []
        Z, Zh = slice(0, N), slice(N, 2 * N)
        for k in range(self.K):
            S = self.Hz[k] @ P @ self.Hz[k].T + self.R[k]
            Lz = np.linalg.solve(S, self.Hz[k] @ P).T
            P = P - Lz @ S @ Lz.T
            current.append(P[:n, :n])
            gains.append(Lz)
            U = np.eye(2 * N + 1)
            U[Zh, Z] += Lz @ self.Hz[k]
            U[Zh, Zh] -= Lz @ self.Hz[k]
            V = np.zeros((2 * N + 1, self.R.shape[1]))
            V[Zh] = Lz
            X = U @ X @ U.T + V @ self.R[k] @ V.T
            stage, X, noise = self._advance(a, k, X, Kh, Z, Zh, n, N, d)
            total += stage
            noises.append(noise)
            Qz = np.zeros((N, N))
            Qz[:n, :n] = noise
            P = self.Az[k] @ P @ self.Az[k].T + Qz
        Tc = np.zeros((N + 1, 2 * N + 1))
        Tc[:N, Z], Tc[N, -1] = np.eye(N), 1.0
        total += np.sum(self._stage_weight(self.K)[:N + 1, :N + 1] * (Tc @ X @ Tc.T))
        return total, np.array(current), np.array(gains), np.array(noises)

    def kalman_for(self, Q):
        """``kalman`` for the motor-noise covariance Q [K, n, n] (the loop's, say): gains Lz [K, N, M]."""
        self.Qz = np.zeros((self.K, self.N, self.N))
        self.Qz[:, :self.n, :self.n] = np.asarray(Q)
        return self.kalman()[0]

    def todorov_sweep(self, Kh, Lz, free=None):
        """Todorov's controller for the fixed filter Lz on xi = [Z; Z_hat; 1]: at each step the
        minimiser over du of the step's Q-function with Z = Z_hat (the filter's errors zero), its
        feedforward held (Kh[:, :, N]) and the rows not ``free`` [K, d] kept; the value is that of
        the new law under the joint system (exact). Returns (Kh_new [K, d, N + 1], its feedback on
        all of Z_hat [K, d, N], the value at xi_0 = [0; 0; 1])."""
        N, d, n, a, K = self.N, self.d, self.n, self.a, self.K
        X1 = 2 * N + 1
        Z, Zh = slice(0, N), slice(N, 2 * N)
        free = np.ones((K, d), bool) if free is None else np.asarray(free)
        Tc = np.zeros((N + 1, X1))
        Tc[:N, Z], Tc[N, -1] = np.eye(N), 1.0
        P = Tc.T @ self._stage_weight(K)[:N + 1, :N + 1] @ Tc
        Kh_new, F_all = np.array(Kh, float), np.zeros((K, d, N))
        xs = n * (self.ls + 1)
        for k in reversed(range(K)):
            S = np.zeros((N + 1 + d, X1 + d))            # [Z; 1; du] from [xi; du]
            S[:N, Z], S[N, X1 - 1], S[N + 1:, X1:] = np.eye(N), 1.0, np.eye(d)
            T = np.zeros((X1, X1 + d))                   # xi^-_{k+1} from [xi; du]
            T[Z, Z], T[Zh, Zh], T[X1 - 1, X1 - 1] = self.Az[k], self.Az[k], 1.0
            T[Z, X1:], T[Zh, X1:] = self.Bz[k], self.Bz[k]
            Qm = S.T @ self._stage_weight(k) @ S + T.T @ P @ T
            Wk = P[:n, :n]                               # the noise enters dx_{k+1} in Z alone
            for j in range(a["c"].shape[1]):
                G = np.zeros((n, X1 + d))
                G[:, X1 - 1] = a["c"][k, j]
                G[:, X1:] = a["C0"][k, j]
                if self.l > 0:
                    G[:, xs:xs + d] += a["C1"][k, j]
                Qm += G.T @ Wk @ G
            # the Q-function on (Z_hat, du) with Z = Z_hat
            E = np.zeros((X1 + d, N + d))
            E[Z, :N], E[Zh, :N], E[X1:, N:] = np.eye(N), np.eye(N), np.eye(d)
            Qy = E.T @ Qm @ E
            Quu, Quy = Qy[N:, N:], Qy[N:, :N]
            F_old = Kh[k, :, :N]
            fr = free[k]
            Quy = Quy + Quu[:, ~fr] @ F_old[~fr]
            F = F_old.copy()
            F[fr] = -np.linalg.solve(Quu[np.ix_(fr, fr)], Quy[fr])
            F_all[k] = F
            Kh_new[k, :, :N] = F
            law = np.zeros((X1 + d, X1))
            law[:X1, :X1] = np.eye(X1)
            law[X1:, Zh], law[X1:, -1] = F, Kh[k, :, N]
            P = law.T @ Qm @ law
            U = np.eye(X1)
            U[Zh, Z] += Lz[k] @ self.Hz[k]
            U[Zh, Zh] -= Lz[k] @ self.Hz[k]
            V = np.zeros((X1, self.R.shape[1]))
            V[Zh] = Lz[k]
            const = np.sum((V.T @ P @ V) * self.R[k])
            P = U.T @ P @ U
            P[-1, -1] += const
            P = 0.5 * (P + P.T)
        return Kh_new, F_all, P[-1, -1]

    def alternate(self, Kh, max_alternations=20, tol=1e-9):
        """The alternation written on the augmented pair: Todorov's controller for the filter of the
        current loop's noise, then the filter of the new loop's noise, kept while the exact cost
        falls. Returns (Kh, costs, the last pair's Cov(dx_k | I_k) [K, n, n])."""
        cost, current = self.loop_kalman_cost(Kh)
        costs = [cost]
        for _ in range(max_alternations):
            Lz, _ = self.loop_kalman_gains(Kh)
            new = self.todorov_sweep(Kh, Lz)[0]
            new_cost, new_current = self.loop_kalman_cost(new)
            if new_cost < cost:
                Kh, current = new, new_current
            done = not new_cost < cost - tol * abs(cost)
            cost = min(cost, new_cost)
            costs.append(cost)
            if done:
                break
        return Kh, np.array(costs), current
