"""The line search's candidates: the nonlinear plant in closed loop around the nominal, under the
delayed law with the feedforward scaled by the step size alpha (``lqg.law.closed_loop_step``):

    u_k = clip(u_bar_k + alpha I_k + L_k (x_k - x_bar_k) + sum_i M_k^i (u_{k+i-l} - u_bar_{k+i-l}))

where u_{k+i-l} are the commands this rollout actually sent (the pending frame keeps their
deviations u - u_bar), so the law feeds back commands already on their way but not yet acting.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._kernels.scan import packed_scan
from ..lqg.frame import SlotGains, current_taps, slot_offsets
from ..problem import Problem
from ..lqg.law import closed_loop_step
from .linearize import delayed_commands

__all__ = ["NominalRow", "StepValues", "nominal_rows", "initial_frame", "nonlinear_step", "closed_loop_rollout"]


class NominalRow(NamedTuple):
    """Step k's data of a closed-loop rollout around the nominal (x_bar, u_bar); time-major in a scan."""

    slot: jax.Array          # (k mod l) d
    x_bar: jax.Array         # [n]
    u_bar: jax.Array         # [d]
    ud_bar: jax.Array        # [d] u_bar_{k-l}
    gains: SlotGains         # row k
    t: jax.Array | None = None   # t_k = k dt; None when the problem does not depend on time


class StepValues(NamedTuple):
    """One step of `nonlinear_step`: the state before it, the command sent and the one acting
    (u_{k-l}), and the new state."""

    x: jax.Array
    u: jax.Array
    ud: jax.Array
    x_new: jax.Array


def nominal_rows(problem: Problem, xs_bar, us_bar, gains: SlotGains) -> NominalRow:
    """The `NominalRow` of every step k = 0..K-1 (time-major)."""
    K, nd = us_bar.shape
    return NominalRow(slot_offsets(K, problem.frame_steps, nd), xs_bar[:-1], us_bar,
                      delayed_commands(problem, us_bar), gains, problem.step_times(us_bar.dtype))


def initial_frame(problem: Problem, dtype):
    """y_0 = [x0; 0]: nothing pending before t = 0."""
    return jnp.concatenate([problem.x0, jnp.zeros(problem.frame_steps * problem.n_controls, dtype)])


def nonlinear_step(problem: Problem, alpha, y, row: NominalRow):
    """One step of the nonlinear plant under u = clip(u_bar + du), du by the law with feedforward
    alpha I; the frame keeps the clipped deviation u - u_bar, and the plant acts on
    u_{k-l} = u_bar_{k-l} + pending slot. Returns (y_{k+1}, `StepValues`)."""
    framed = problem.delay_frame is not None

    def plant(x, du, du_delayed):
        u = jnp.clip(row.u_bar + du, problem.u_min, problem.u_max)
        if du_delayed is None:      # a frame of no slots: every delay is 0
            ud = u
        elif framed:      # l is data
            ud = jnp.where(problem.delay_steps == 0, current_taps(u, problem.delay_steps), row.ud_bar + du_delayed)
        else:
            ud = row.ud_bar + du_delayed if problem.delay_steps > 0 else u
        x_new = x + problem.dt * problem.dynamics_at(x, u, ud, row.t)
        return x_new, u - row.u_bar, StepValues(x, u, ud, x_new)

    gains = SlotGains(alpha * row.gains.feedforward, row.gains.feedback)
    return closed_loop_step(y, row.slot, gains, plant, problem.n_states, row.x_bar,
                            problem.delay_steps if framed else None)


def closed_loop_rollout(problem: Problem, xs_bar, us_bar, gains: SlotGains, alpha):
    """Noise-free rollout of the nonlinear plant under the delayed law; returns (xs [K+1, n], us [K, d])."""
    def step(y, row):
        y_new, values = nonlinear_step(problem, alpha, y, row)
        # x_new, not x: the new state is made once for both the carry and the output, where with x
        # XLA recomputes the dynamics in a second fusion (docs/performance.md#x_new-in-closed_loop_rollout)
        return y_new, (values.x_new, values.u)

    # inputs unpacked: their packed copy would be the solver's largest temporary
    # (docs/performance.md#pack_inputsfalse-in-the-closed-loop-rollout-and-the-candidate-scores)
    _, (xs, us) = packed_scan(step, initial_frame(problem, us_bar.dtype), nominal_rows(problem, xs_bar, us_bar, gains),
                              pack_inputs=False)
    return jnp.concatenate([problem.x0[None], xs]), us
