"""Independent references for delayed sensing, written densely in numpy on the augmented state

    Z_k = [dx_k, dx_{k-1}, ..., dx_{k-l_s}, du_{k-l}, ..., du_{k-1}]        (N = n (l_s + 1) + l d)

on which the plant is an ordinary undelayed linear system and the measurement dy_k = H_k dx_{k-l_s}
+ G_k v_k an ordinary undelayed one. Nothing here calls the library's recursions: the Kalman filter,
the LQR and the exact second moments of (Z, Z_hat) are the textbook ones.
"""
from __future__ import annotations

import numpy as np

from delayed_ilqr.lqg import DelayedLQG, DelayedObservation


def random_problem(seed, K, n, d, m, q, p, l, ls, *, mult_noise=0.0):
    """A random convex time-varying delayed LQG (as tests/test_lqg.py draws them) and a random
    observation with G G' positive definite."""
    rng = np.random.default_rng(seed)
    s = n + d + 1
    X = rng.standard_normal((K + 1, s, s))
    W = X @ np.swapaxes(X, 1, 2) / s + np.diag(np.r_[np.full(n, 0.1), np.full(d, 0.1), 0.1])
    lqg = DelayedLQG(
        A=0.8 * np.eye(n) + 0.4 * rng.standard_normal((K, n, n)) / np.sqrt(n),
        B0=rng.standard_normal((K, n, d)) / np.sqrt(n), B1=rng.standard_normal((K, n, d)) / np.sqrt(n),
        c=0.3 * rng.standard_normal((K, p, n)),
        C0=mult_noise * rng.standard_normal((K, p, n, d)), C1=mult_noise * rng.standard_normal((K, p, n, d)),
        d_tilde=W[:, -1, -1], d=W[:, :n, -1], D=W[:, :n, :n], e=W[:-1, n:n + d, -1], E=W[:-1, n:n + d, n:n + d],
        N=W[:-1, n:n + d, :n], delay_steps=l)
    G = 0.3 * rng.standard_normal((K, m, q))
    G[:, :, :m] += 0.2 * np.eye(m)
    obs = DelayedObservation(H=rng.standard_normal((K, m, n)), G=G, delay_steps=ls)
    return lqg, obs


class Augmented:
    """The plant and the sensors on Z (numpy), with l = 0 read as B1, C1 acting on du_k."""

    def __init__(self, lqg: DelayedLQG, obs: DelayedObservation):
        a = {f: np.asarray(getattr(lqg, f)) for f in ("A", "B0", "B1", "c", "C0", "C1", "d_tilde", "d", "D", "e",
                                                      "E", "N")}
        self.l, self.ls = l, ls = lqg.delay_steps, obs.delay_steps
        if l == 0:
            a["B0"], a["B1"] = a["B0"] + a["B1"], 0 * a["B1"]
            a["C0"], a["C1"] = a["C0"] + a["C1"], 0 * a["C1"]
        self.a = a
        self.K, self.n, self.d = K, n, d = lqg.horizon, lqg.n_states, lqg.n_controls
        self.N = N = n * (ls + 1) + l * d
        self.H, self.R = np.asarray(obs.H), np.asarray(obs.measurement_cov)
        self.Az = np.zeros((K, N, N))
        self.Bz = np.zeros((K, N, d))
        self.Hz = np.zeros((K, self.H.shape[1], N))
        xs = n * (ls + 1)                                     # first entry of the pending commands
        for k in range(K):
            self.Az[k, :n, :n] = a["A"][k]
            self.Bz[k, :n] = a["B0"][k]
            self.Az[k, n:xs, :xs - n] = np.eye(xs - n)       # the history shifts by one
            if l > 0:
                self.Az[k, :n, xs:xs + d] = a["B1"][k]       # du_{k-l} acts now
                self.Az[k, xs:N - d, xs + d:] = np.eye((l - 1) * d)
                self.Bz[k, N - d:] = np.eye(d)
            self.Hz[k, :, ls * n:xs] = self.H[k]
        self.Qz = np.zeros((K, N, N))
        self.Qz[:, :n, :n] = np.einsum("kpn,kpm->knm", a["c"], a["c"])

    def block(self, i):
        """The entries of dx_{k-i} in Z."""
        return slice(i * self.n, (i + 1) * self.n)

    def kalman(self):
        """The Kalman filter on Z: gains Lz [K, N, m] (zero before a measurement arrives), priors
        and posteriors [K, N, N], innovation covariances [K, m, m], and the terminal prior [N, N]."""
        K, N, m = self.K, self.N, self.H.shape[1]
        P = np.zeros((N, N))                                  # x0 known: Z_0 = 0 exactly
        Lz, priors, posts, S_all = np.zeros((K, N, m)), np.zeros((K, N, N)), np.zeros((K, N, N)), np.zeros((K, m, m))
        for k in range(K):
            priors[k] = P
            S = self.Hz[k] @ P @ self.Hz[k].T + self.R[k]
            S_all[k] = S
            if k >= self.ls:
                Lz[k] = np.linalg.solve(S, self.Hz[k] @ P).T
                P = P - Lz[k] @ S @ Lz[k].T
            posts[k] = P
            P = self.Az[k] @ P @ self.Az[k].T + self.Qz[k]
        return Lz, priors, posts, S_all, P

    def estimates(self, Lz, du, dy):
        """The augmented filter run on one record: Z_hat_k given I_k, [K, N]."""
        Zh, out = np.zeros(self.N), []
        for k in range(self.K):
            Zh = Zh + Lz[k] @ (dy[k] - self.Hz[k] @ Zh)
            out.append(Zh)
            Zh = self.Az[k] @ Zh + self.Bz[k] @ du[k]
        return np.array(out)

    def _stage_weight(self, k):
        """W with cost_k = [Z; 1; du]' W [Z; 1; du] (eq. 4), [N + 1 + d, N + 1 + d]."""
        a, n, N, d = self.a, self.n, self.N, self.d
        W = np.zeros((N + 1 + d, N + 1 + d))
        W[:n, :n], W[:n, N], W[N, :n], W[N, N] = a["D"][k], a["d"][k], a["d"][k], a["d_tilde"][k]
        if k < self.K:
            u = slice(N + 1, N + 1 + d)
            W[u, u], W[u, N], W[N, u] = a["E"][k], a["e"][k], a["e"][k]
            W[u, :n], W[:n, u] = a["N"][k], a["N"][k].T
        return W

    def lqr(self):
        """The optimal full-information law du_k = Kh_k [Z_k; 1] [K, d, N + 1] (additive noise) and
        its cost V_0 at Z_0 = 0."""
        N, d = self.N, self.d
        V = self._stage_weight(self.K)[:N + 1, :N + 1]
        Kh = np.zeros((self.K, d, N + 1))
        for k in reversed(range(self.K)):
            Ah = np.zeros((N + 1, N + 1))
            Ah[:N, :N], Ah[N, N] = self.Az[k], 1.0
            Bh = np.vstack([self.Bz[k], np.zeros((1, d))])
            W = self._stage_weight(k)
            Quu = W[N + 1:, N + 1:] + Bh.T @ V @ Bh
            Qux = W[N + 1:, :N + 1] + Bh.T @ V @ Ah
            Qxx = W[:N + 1, :N + 1] + Ah.T @ V @ Ah
            Qxx[N, N] += np.sum(V[:N, :N] * self.Qz[k])
            Kh[k] = -np.linalg.solve(Quu, Qux)
            V = Qxx + Qux.T @ Kh[k]
            V = 0.5 * (V + V.T)
        return Kh, V[N, N]

    def transport(self, k, i):
        """Phi(k - i, k - l_s) = A_{k-i-1} ... A_{k-l_s} (identity before time 0)."""
        Phi = np.eye(self.n)
        for j in range(k - self.ls, k - i):
            Phi = (self.a["A"][j] if j >= 0 else np.eye(self.n)) @ Phi
        return Phi

    def policy(self, gains, delayed_gain):
        """The library's law ``gains`` on [Z_hat; 1] (Kh), and the filter whose innovation gain on
        dx_{k-i} is Phi(k-i, k-l_s) Kd_k for every i = 0..l_s (Lz): the family of estimators that
        predict every state after k - l_s from the delayed estimate. Returns (Kh, Lz, Kc)."""
        K, n, N, ls = self.K, self.n, self.N, self.ls
        I, L, M = (np.asarray(g) for g in gains)
        Kd = np.asarray(delayed_gain)
        Kh = np.zeros((K, self.d, N + 1))
        Lz = np.zeros((K, N, Kd.shape[2]))
        for k in range(K):
            Kh[k, :, :n], Kh[k, :, N] = L[k], I[k]
            for i in range(self.l):
                Kh[k, :, n * (ls + 1) + i * self.d:n * (ls + 1) + (i + 1) * self.d] = M[k, i]
            if k >= ls:
                for i in range(ls + 1):
                    Lz[k, self.block(i)] = self.transport(k, i) @ Kd[k]
        return Kh, Lz, Lz[:, self.block(0)]

    def _advance(self, a, k, X, Kh, Z, Zh, n, N, d):
        """Step k of the pair's second moment X [2N + 1, 2N + 1] under the law Kh: its stage cost,
        X at k + 1 (the motor noise of the commands added) and that noise [n, n]."""
        Tc = np.zeros((N + 1 + d, 2 * N + 1))          # [Z; 1; du] from xi
        Tc[:N, Z], Tc[N, -1] = np.eye(N), 1.0
        Tc[N + 1:, Zh], Tc[N + 1:, -1] = Kh[k, :, :N], Kh[k, :, N]
        stage = np.sum(self._stage_weight(k) * (Tc @ X @ Tc.T))
        noise = np.zeros((n, n))
        for j in range(a["c"].shape[1]):
            Gj = np.zeros((n, 2 * N + 1))
            Gj[:, -1] = a["c"][k, j]
            Gj += a["C0"][k, j] @ Tc[N + 1:]
            if self.l > 0:                                # du_{k-l}: the oldest command in flight
                xs = n * (self.ls + 1)
                Gj[:, xs:xs + d] += a["C1"][k, j]
            noise += Gj @ X @ Gj.T
        T = np.zeros((2 * N + 1, 2 * N + 1))
        T[Z, Z], T[Zh, Zh], T[-1, -1] = self.Az[k], self.Az[k], 1.0
        T[Z] += self.Bz[k] @ Tc[N + 1:]
        T[Zh] += self.Bz[k] @ Tc[N + 1:]
        X = T @ X @ T.T
        X[:n, :n] += noise
        return stage, X, noise

    def output_feedback_cost(self, Kh, Lz):
        """Exact E[cost] of du_k = Kh_k [Z_hat_k; 1] with the filter gains Lz, by the second
        moment of xi = [Z; Z_hat; 1], with the motor noise columns c_j + C0_j du_k + C1_j du_{k-l}."""
        N, d, n, a = self.N, self.d, self.n, self.a
        X = np.zeros((2 * N + 1, 2 * N + 1))
        X[-1, -1] = 1.0
        total = 0.0
        Z, Zh = slice(0, N), slice(N, 2 * N)
        for k in range(self.K):
            U = np.eye(2 * N + 1)
            U[Zh, Z] += Lz[k] @ self.Hz[k]
            U[Zh, Zh] -= Lz[k] @ self.Hz[k]
            V = np.zeros((2 * N + 1, self.R.shape[1]))
            V[Zh] = Lz[k]
            X = U @ X @ U.T + V @ self.R[k] @ V.T
            stage, X, _ = self._advance(a, k, X, Kh, Z, Zh, n, N, d)
            total += stage
        Tc = np.zeros((N + 1, 2 * N + 1))
        Tc[:N, Z], Tc[N, -1] = np.eye(N), 1.0
        return total + np.sum(self._stage_weight(self.K)[:N + 1, :N + 1] * (Tc @ X @ Tc.T))

