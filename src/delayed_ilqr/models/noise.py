"""The noise convention of the package, and the conversion from the per-step convention.

This package's noise F(x, u, ud) is a **continuous-time diffusion** (the paper's eq. 1,
dx = f dt + F dw). One Euler step of length dt adds ``sqrt(dt) F(x_k, u_k, u_{k-l}) xi_k``,
xi_k ~ N(0, I_p), so the per-step covariance of the noise is ``dt F F'``. For signal-dependent
noise F = sigma_u G diag(ud) (G the input matrix, e.g. M(q)^{-1} of the arm) a held command u has a
per-step relative standard deviation ``sigma_u / sqrt(dt)`` (2.0 for sigma_u = 0.2 at dt = 10 ms).

Todorov's discrete-time models and code (Todorov 2005, ``docs/models.md`` §2.1-2.2 and §4.5:
x_{t+1} = A x + B u + sum_i eps_i C_i u with C_i = sigma_c B, sigma_c = 0.5 at dt = 10 ms) instead
scale the command's effect on one step by ``1 + sigma eps``, eps ~ N(0, 1), i.e.
``x_{k+1} = x_k + dt (f + G u_k) + dt G sigma diag(u_k) eps_k``: sigma is per step and the
per-step covariance is ``dt^2 sigma^2 G diag(u)^2 G'``. (Li's thesis torque arm, as reimplemented
in ``nioc``, already writes ``sqrt(dt) G sigma_u diag(u) xi``, this package's convention.) The two agree when
``sigma_u = sigma sqrt(dt)``: [`per_step_noise_to_diffusion`][delayed_ilqr.models.per_step_noise_to_diffusion]. Entering a per-step sigma as
``sigma_u`` multiplies the noise's standard deviation by ``1 / sqrt(dt)`` (10 at dt = 10 ms):
Todorov's sigma = 0.5 is sigma_u = 0.05 here, not 0.5.
"""
from __future__ import annotations

import math

from . import _common

__all__ = ["per_step_noise_to_diffusion", "diffusion_to_per_step"]


def per_step_noise_to_diffusion(sigma, dt) -> float:
    """The diffusion scale sigma_u of this package equal to a per-step relative noise sigma.

    Args:
        sigma: relative standard deviation of the command's effect in one step of length ``dt``
            (the discrete-time convention of Todorov's code), >= 0.
        dt: the step (s) the per-step sigma refers to, > 0.

    Returns:
        sigma_u = sigma sqrt(dt), to pass as a model's ``sigma_u`` (the per-step variances agree:
        ``dt (sigma_u G u)^2 = (dt sigma G u)^2``).
    """
    return _common.non_negative(sigma, "sigma") * math.sqrt(_common.positive(dt, "dt"))


def diffusion_to_per_step(sigma_u, dt) -> float:
    """The inverse of [`per_step_noise_to_diffusion`][delayed_ilqr.models.per_step_noise_to_diffusion]: sigma = sigma_u / sqrt(dt)."""
    return _common.non_negative(sigma_u, "sigma_u") / math.sqrt(_common.positive(dt, "dt"))
