"""The exact expected cost of any affine delayed policy, and Monte Carlo of the linear system.

[`policy_cost`][delayed_ilqr.lqg.policy_cost] propagates the mean and second moment of the augmented state z_k (no sampling):
the reference that every backward pass's J(0) is checked against; [`closed_loop_moments`][delayed_ilqr.lqg.closed_loop_moments]
returns those moments. [`simulate_lqg`][delayed_ilqr.lqg.simulate_lqg] estimates
the same expectation by sampling the noise.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import _precision, _validate
from .law import augmented_feedback, closed_loop_affine, delayed_law
from .augmented import augment
from .model import DelayedLQG, Gains, checked_entry, merged_if_undelayed

__all__ = ["policy_cost", "closed_loop_moments", "Moments", "simulate_lqg", "LQGRuns", "checked_gains"]


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def checked_gains(lqg: DelayedLQG, gains: Gains) -> Gains:
    """``gains`` as arrays, after checking their shapes against ``lqg`` and that they are finite."""
    K, nx, nd, l = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.frame_steps
    return Gains(
        jnp.asarray(_validate.array(gains.feedforward, "gains.feedforward", (K, nd))),
        jnp.asarray(_validate.array(gains.state_feedback, "gains.state_feedback", (K, nd, nx))),
        jnp.asarray(_validate.array(gains.delay_feedback, "gains.delay_feedback", (K, l, nd, nd))))


class Moments(NamedTuple):
    """The mean and second moment of the augmented state z_k = [dx_k, du_{k-l}, ..., du_{k-1}] of
    the linear closed loop, from z_0 = 0 (exact, no sampling).

    Attributes:
        mean: [K+1, n + l d] E[z_k].
        second: [K+1, n + l d, n + l d] E[z_k z_k'] (the covariance is second - mean mean').
    """

    mean: jax.Array
    second: jax.Array

    def state_covariance(self, n: int) -> jax.Array:
        """[K+1, n, n] Cov(dx_k)."""
        mu = self.mean[:, :n]
        return self.second[:, :n, :n] - mu[:, :, None] * mu[:, None, :]


def _moments_and_cost(lqg: DelayedLQG, gains: Gains):
    """(Moments, E[J(0)]) of the affine delayed policy ``gains`` on ``lqg``: one forward scan."""
    aug = augment(lqg)
    Kz = augmented_feedback(gains)                                    # [K, d, n + l d]
    nz = Kz.shape[2]

    def step(carry, data):
        mu, X, total = carry
        Az, Bz, cz, Cz, Cu, I, Kk, d_tilde, dz, Dz, e, E, Nz = data
        Eu = delayed_law(I, Kk, mu)                                   # E[du]: the law is affine
        Euu = jnp.outer(I, I) + Kk @ jnp.outer(mu, I) + jnp.outer(I, mu) @ Kk.T + Kk @ X @ Kk.T
        Ezu = jnp.outer(mu, I) + X @ Kk.T                              # E[z du']
        total = total + d_tilde + 2 * dz @ mu + jnp.sum(Dz * X) + 2 * e @ Eu + jnp.sum(E * Euu) \
            + 2 * jnp.sum(Nz.T * Ezu)
        Acl, bcl = closed_loop_affine(Az, Bz, I, Kk)                  # z' = Acl z + bcl + noise
        Gcol, CuI = closed_loop_affine(Cz, Cu, I, Kk)                 # [p, n + l d, n + l d], [p, n + l d]
        gcol = cz + CuI                                               # noise column j: Gcol_j z + gcol_j
        mu_new = Acl @ mu + bcl
        Am = Acl @ mu
        X_new = Acl @ X @ Acl.T + jnp.outer(Am, bcl) + jnp.outer(bcl, Am) + jnp.outer(bcl, bcl)
        Gm = jnp.einsum("pnk,k->pn", Gcol, mu)
        X_new = X_new + jnp.einsum("pnk,kl,pml->nm", Gcol, X, Gcol) + jnp.einsum("pn,pm->nm", Gm, gcol) \
            + jnp.einsum("pn,pm->nm", gcol, Gm) + jnp.einsum("pn,pm->nm", gcol, gcol)
        X_new = _sym(X_new)
        return (mu_new, X_new, total), (mu_new, X_new)

    dt = lqg.A.dtype
    init = (jnp.zeros(nz, dt), jnp.zeros((nz, nz), dt), jnp.asarray(0.0, dt))
    data = (aug["Az"], aug["Bz"], aug["cz"], aug["Cz"], aug["Cu"], gains.feedforward, Kz,
            lqg.d_tilde[:-1], aug["dz"][:-1], aug["Dz"][:-1], lqg.e, lqg.E, aug["Nz"])
    (mu, X, total), (mus, Xs) = jax.lax.scan(step, init, data)
    moments = Moments(jnp.concatenate([init[0][None], mus]), jnp.concatenate([init[1][None], Xs]))
    return moments, total + lqg.d_tilde[-1] + 2 * aug["dz"][-1] @ mu + jnp.sum(aug["Dz"][-1] * X)


@jax.jit
def _policy_cost(lqg: DelayedLQG, gains: Gains):
    return _moments_and_cost(lqg, gains)[1]


def closed_loop_moments(lqg: DelayedLQG, gains: Gains) -> Moments:
    """The exact [`Moments`][delayed_ilqr.lqg.Moments] of the augmented state under the affine delayed policy ``gains``
    on ``lqg`` (the propagation of [`policy_cost`][delayed_ilqr.lqg.policy_cost], control-dependent noise included), from
    z_0 = 0. Differentiable (a scan); not validated, for use inside traced code
    (``delayed_ilqr.prediction``)."""
    return _moments_and_cost(lqg, gains)[0]


def policy_cost(lqg: DelayedLQG, gains: Gains) -> jax.Array:
    """Exact E[J(0)] of the affine delayed policy ``gains`` on ``lqg`` (no sampling).

    Propagates the mean mu_k and second moment X_k = E[z_k z_k'] of the augmented state z_k
    through the closed loop, including the control-dependent noise, and sums the expected costs.
    Cost O(K (n + l d)^3): a reference, not a hot path.
    """
    _precision.require_x64("lqg.policy_cost")
    checked_entry(lqg, 0.0, "lqg.policy_cost")
    return _policy_cost(lqg, checked_gains(lqg, gains))


class LQGRuns(NamedTuple):
    """Monte Carlo trials of the linear delayed system.

    Attributes: dx [n_trials, K+1, n], du [n_trials, K, d], cost [n_trials] (eq. 4 summed over
    k = 0..K per trial).
    """

    dx: jax.Array
    du: jax.Array
    cost: jax.Array


@partial(jax.jit, static_argnames=("n_trials",))
def _simulate_lqg(lqg: DelayedLQG, gains: Gains, n_trials: int, key):
    lqg = merged_if_undelayed(lqg)
    K, nx, nd, p, slots = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.n_noise, lqg.frame_steps
    # pending holds du_{k-slots} .. du_{k-1}; the command acting is pending[0], or with a frame of L
    # slots pending[L - l] (clipped for l = 0, where B1 = C1 = 0 and it is unused); with per-channel
    # delays channel j's component of pending[L - l_j]
    acting = 0 if lqg.delay_frame is None else jnp.minimum(slots - lqg.delay_steps, max(slots - 1, 0))
    dt = lqg.A.dtype

    def trial(trial_key):
        xi = jax.random.normal(trial_key, (K, p), dt)

        def step(carry, data):
            dx, pending = carry                                       # pending[i] = du_{k+i-slots}
            A, B0, B1, c, C0, C1, I, LM, xik, d_tilde, dv, D, e, E, Nxu = data
            du = delayed_law(I, LM, jnp.concatenate([dx, pending.reshape(-1)]))
            du_delayed = pending[acting, jnp.arange(nd)] if slots > 0 else jnp.zeros(nd, dt)   # [d] per channel
            noise = xik @ (c + C0 @ du + C1 @ du_delayed)
            dx_new = A @ dx + B0 @ du + B1 @ du_delayed + noise
            cost = d_tilde + 2 * dx @ dv + dx @ D @ dx + 2 * du @ e + du @ E @ du + 2 * du @ Nxu @ dx
            pending = jnp.concatenate([pending[1:], du[None]]) if slots > 0 else pending
            return (dx_new, pending), (dx, du, cost)

        data = (lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, gains.feedforward, augmented_feedback(gains), xi,
                lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1], lqg.e, lqg.E, lqg.N)
        (dxK, _), (dx, du, cost) = jax.lax.scan(step, (jnp.zeros(nx, dt), jnp.zeros((slots, nd), dt)), data)
        final = lqg.d_tilde[-1] + 2 * dxK @ lqg.d[-1] + dxK @ lqg.D[-1] @ dxK
        return jnp.concatenate([dx, dxK[None]]), du, jnp.sum(cost) + final

    return LQGRuns(*jax.vmap(trial)(jax.random.split(key, n_trials)))


def simulate_lqg(lqg: DelayedLQG, gains: Gains, n_trials: int, seed: int = 0) -> LQGRuns:
    """Monte Carlo of the linear delayed system (3) under ``gains``, vectorised over trials."""
    _precision.require_x64("lqg.simulate_lqg")
    checked_entry(lqg, 0.0, "lqg.simulate_lqg")
    n_trials = _validate.positive_int(n_trials, "n_trials")
    seed = _validate.seed(seed)
    return _simulate_lqg(lqg, checked_gains(lqg, gains), n_trials, jax.random.PRNGKey(seed))
