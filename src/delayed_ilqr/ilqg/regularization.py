"""Tassa's regularisation schedule: lambda and its multiplier grow geometrically after a failure
and shrink after a success; lambda below ``reg_min`` is set to 0 (the exact Newton step)."""
from __future__ import annotations

import jax.numpy as jnp

from ..options import Options

__all__ = ["increase", "decrease", "update"]


def increase(reg, dreg, o: Options):
    """(lambda, its multiplier) after a failed iteration."""
    dreg = jnp.maximum(dreg * o.reg_factor, o.reg_factor)
    return jnp.maximum(reg * dreg, o.reg_min), dreg


def decrease(reg, dreg, o: Options):
    """(lambda, its multiplier) after an accepted step."""
    dreg = jnp.minimum(dreg / o.reg_factor, 1.0 / o.reg_factor)
    reg = reg * dreg
    return jnp.where(reg > o.reg_min, reg, 0.0), dreg


def update(reg, dreg, accept, hold, o: Options):
    """(lambda, multiplier) for the next iteration: decreased after an accepted step, kept where
    ``hold`` (the solve stops: converged, or the model predicts too little), increased otherwise."""
    reg_up, dreg_up = increase(reg, dreg, o)
    reg_down, dreg_down = decrease(reg, dreg, o)
    return (jnp.where(accept, reg_down, jnp.where(hold, reg, reg_up)),
            jnp.where(accept, dreg_down, jnp.where(hold, dreg, dreg_up)))
