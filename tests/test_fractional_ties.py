"""The derivative of a fractional delay's step in phi where a piece has zero width: a whole step
(phi_j = 0) and equal fractions on two channels (docs/derivation.md §20).

There the step is still differentiable in phi for a plant linear in its delayed commands, and
one-sidedly for any plant; the references are independent of the two-tap code: the derivative
written out for a drift linear in ud, d f_bar / d phi_j = f(.., older_j, ..) - f(.., newer_j, ..),
and one-sided finite differences of the step for a drift that couples the channels nonlinearly.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from delayed_ilqr._fractional import diffusion, drift

from test_fractional import _coupled, _coupled_noise   # tests/test_fractional.py: nonlinear, coupled

jax.config.update("jax_enable_x64", True)

# whole steps and ties: every fraction pattern at which a piece has zero width
ZERO_WIDTH = ([0.0, 0.0, 0.0], [0.0, 0.3, 0.7], [0.4, 0.4, 0.8], [0.5, 0.2, 0.5], [0.0, 0.6, 0.0])


def _affine(x, u, ud):
    """A drift linear in the delayed commands: the step is then smooth in phi at any pattern."""
    B = jnp.array([[1.0, -2.0, 0.5], [0.3, 0.7, -1.1], [2.0, 0.1, 0.4]])
    return jnp.array([x[1], -x[0], x[2] * u[0]]) + B @ ud


@pytest.mark.parametrize("phi", ZERO_WIDTH)
def test_derivative_in_phi_at_a_zero_width_piece(phi):
    """Linear in ud: jax.jacobian of the step in phi equals the derivative written out, column by
    column, where a piece has zero width (before the held commands came from the ranks, column j
    was zero at phi_j = 0)."""
    rng = np.random.default_rng(1)
    x, u = rng.standard_normal(3), rng.standard_normal(3)
    newer, older = rng.standard_normal(3), rng.standard_normal(3)
    ud2 = jnp.concatenate([newer, older])
    jac = jax.jacobian(lambda p: drift(_affine, x, u, ud2, p))(jnp.asarray(phi))
    for j in range(3):
        switched = newer.copy()
        switched[j] = older[j]
        reference = _affine(x, u, switched) - _affine(x, u, newer)
        np.testing.assert_allclose(jac[:, j], reference, rtol=1e-13, atol=1e-13)


def test_right_derivative_at_a_whole_step_of_a_nonlinear_step():
    """Coupled nonlinearly: at phi_0 = 0 (the other fractions apart) the derivatives in phi_0 of the
    drift and of the step's covariance F F' are the right-hand ones. Both are linear in phi_0 until
    it meets the next fraction, so a forward difference of step h < 0.35 is exact to round-off.
    (Before, the covariance's derivative left out the new piece's noise there.)"""
    rng = np.random.default_rng(2)
    x, u = rng.standard_normal(3), rng.standard_normal(3)
    ud2 = jnp.asarray(rng.standard_normal(6))
    phi = jnp.array([0.0, 0.35, 0.8])
    cov = lambda p: diffusion(_coupled_noise, x, u, ud2, p) @ diffusion(_coupled_noise, x, u, ud2, p).T  # noqa: E731
    for step in (lambda p: drift(_coupled, x, u, ud2, p), cov):
        jac = jax.jacobian(step)(phi)[..., 0]
        h = 0.25
        difference = (step(phi.at[0].set(h)) - step(phi)) / h
        np.testing.assert_allclose(jac, difference, rtol=1e-12, atol=1e-12)
        assert float(jnp.max(jnp.abs(jac))) > 0.1                       # not the zero of the old code
