"""The noise convention: a per-step sigma (Todorov's discrete-time code) converted by
``per_step_noise_to_diffusion`` gives the same per-step variance as this package's diffusion."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from delayed_ilqr.models import (arm2, arm2_muscle6, diffusion_to_per_step, mass_matrix_inverse,
                                 per_step_noise_to_diffusion)
from delayed_ilqr.models.arm2 import SIGMA_U, SIGMA_U_HUMAN


@pytest.mark.parametrize("dt", [0.01, 0.002])
def test_per_step_sigma_and_converted_diffusion_give_the_same_step_variance(dt):
    sigma = 0.5                                                       # Todorov 2005's per-step value
    sigma_u = per_step_noise_to_diffusion(sigma, dt)
    assert sigma_u == pytest.approx(sigma * math.sqrt(dt), rel=1e-15)
    assert diffusion_to_per_step(sigma_u, dt) == pytest.approx(sigma, rel=1e-15)
    p = arm2(noise=True, dt=dt, sigma_u=sigma_u)
    x = jnp.array([0.7, 1.2, 0.3, -0.2])
    ud = jnp.array([1.5, -0.8])
    # this package: one step adds sqrt(dt) F xi, covariance dt F F'
    F = p.noise(x, ud, ud)
    ours = dt * F @ F.T
    # Todorov's per-step convention: x+ = x + dt (f + G ud (1 + sigma eps)), G = M(q)^{-1} on the velocities
    G = np.vstack([np.zeros((2, 2)), np.asarray(mass_matrix_inverse(x[:2]))])
    step_noise = dt * G * (sigma * np.asarray(ud))[None, :]           # column j: the effect of eps_j
    theirs = step_noise @ step_noise.T
    np.testing.assert_allclose(np.asarray(ours), theirs, rtol=1e-12, atol=1e-20)
    # the sampled variance of one Euler step of the simulator agrees too (both draw xi ~ N(0, I))
    xi = jax.random.normal(jax.random.PRNGKey(0), (200_000, 2), jnp.float64)
    steps = np.asarray(math.sqrt(dt) * xi @ F.T)
    np.testing.assert_allclose(np.var(steps[:, 2:], axis=0), np.diag(theirs)[2:], rtol=0.02)


def test_entering_a_per_step_sigma_unconverted_is_sqrt_dt_times_too_large():
    dt = 0.01
    wrong = arm2(noise=True, sigma_u=0.5).noise(jnp.zeros(4), jnp.ones(2), jnp.ones(2))
    right = arm2(noise=True, sigma_u=per_step_noise_to_diffusion(0.5, dt)).noise(jnp.zeros(4), jnp.ones(2), jnp.ones(2))
    np.testing.assert_allclose(np.asarray(wrong), np.asarray(right) / math.sqrt(dt), rtol=1e-12)


def test_default_noise_levels():
    """P2-noisy (noise="benchmark") keeps its benchmark sigma_u = 0.2; noise=True is the
    human-calibrated level 0.01, whose activation (or torque filtered at the activation time
    constant) has a 2.8-3.2 % coefficient of variation (docs/models.md §4.5)."""
    assert SIGMA_U == 0.2 and arm2(noise="benchmark").noise.sigma_u == 0.2
    assert arm2(noise=True).noise.sigma_u == SIGMA_U_HUMAN == 0.01
    assert arm2_muscle6(noise=True).noise.sigma_u == 0.01
    for t in (0.05, 0.066):
        cv = SIGMA_U_HUMAN / math.sqrt(2 * t)
        assert 0.027 < cv < 0.033
    with pytest.raises(ValueError, match="sigma_u"):
        arm2(noise=True, sigma_u=-0.1)
