"""The fused filter of a policy whose sensors have different delays (``lqg.fusion``).

It runs on deviations from the policy's nominal (``docs/derivation.md`` §19). The measurements are
kept by the time j of the state they sense, over the window j = k-W..k (W the largest delay):

    x_b     <- A x_b + B0 du + B1 du_{-l} + Kb_{k-W} (z_{k-W} - H_{k-W} x_b)        E[dx_{k-W} | z_{<=k-W}]
    x       <- x_b, then for j = k-W+1..k:
    x       <- A_{j-1} x + B0_{j-1} du_{j-1} + B1_{j-1} du_{j-1-l} + Wg_{k,j} (z_j - H_j x)
    x_hat_k  = x                                                                  E[dx_k | I_k]

with z_j the rows of every sensor that sense x_j and have arrived (sensor a's at step j + l_a,
minus their nominal), and the gains zero on rows not yet arrived or not sampled.
"""
from __future__ import annotations

import jax

__all__ = ["FusedEstimator"]


class FusedEstimator:
    """The fused Kalman filter of several delayed sensors, designed around a policy's nominal.

    Attributes:
        A: [K, n, n]; B0, B1: [K, n, d]: the model the estimates move with.
        H: [K, M, n] the stacked sensor rows in state time j (row block a: dh_a/dx at x_nominal_j,
            zero where sensor a does not sample x_j).
        y_nominal: [K, M] the nominal of the rows arriving at step k (block a: h_a(x_nominal_{k-l_a})).
        base_gain: [K, n, M] Kb_j; window_gain: [K, W, n, M] Wg_k.
        error_covariance: [K+1, n, n] Cov(dx_k - x_hat_k) of the linearised closed loop (exact,
            signal-dependent motor noise included; row K: the terminal state given I_{K-1}).
        lags: the delay of each row (static: a pytree's aux data).
    """

    _arrays = ("A", "B0", "B1", "H", "y_nominal", "base_gain", "window_gain", "error_covariance")

    def __init__(self, A, B0, B1, H, y_nominal, base_gain, window_gain, error_covariance, lags):
        self.A, self.B0, self.B1, self.H, self.y_nominal = A, B0, B1, H, y_nominal
        self.base_gain, self.window_gain, self.error_covariance = base_gain, window_gain, error_covariance
        self.lags = tuple(int(v) for v in lags)

    @property
    def window(self) -> int:
        """W, the largest delay (clipped to the horizon)."""
        return self.window_gain.shape[-3]

    @property
    def n_outputs(self) -> int:
        return self.H.shape[-2]

    def replace(self, **changes) -> "FusedEstimator":
        fields = {name: getattr(self, name) for name in self._arrays + ("lags",)}
        fields.update(changes)
        return FusedEstimator(**fields)

    def __repr__(self):
        return (f"FusedEstimator(K={self.H.shape[-3]}, n={self.A.shape[-1]}, m={self.n_outputs}, "
                f"lags={sorted(set(self.lags))})")


jax.tree_util.register_pytree_node(
    FusedEstimator,
    lambda e: (tuple(getattr(e, name) for name in FusedEstimator._arrays), e.lags),
    lambda lags, arrays: FusedEstimator(*arrays, lags=lags))
