"""The bounded step: with control limits and no noise, each iteration's step is the minimiser of the
LQG model over the box, and the law the line search rolls out has that minimiser as its plan.

The LQG of one iteration (eq. 3-4) is, as a function of the open-loop command deviations
du = [du_0, ..., du_{K-1}] (dx_0 = 0, x driven by du_k and du_{k-l}), a convex quadratic J(du)
whenever every H_k + lambda I of the backward pass is positive definite (the recursion is a block
factorisation of its Hessian). The box is u_min - u_bar_k <= du_k <= u_max - u_bar_k. Box-DDP
(Tassa, Mansard & Todorov 2014) solves one small box QP per step at y = 0 instead, and the law's
plan (the LQG's own closed loop) leaves the box wherever the feedback of a free command pushes it
out; the forward pass clips it there and the line search fails (docs/derivation.md §15).

Here J is minimised over the box by Bertsekas' (1982) projected Newton method, from du = 0:

1. the epsilon-active set A at du: commands within ``eps`` of a bound whose gradient points out;
2. the Newton point N: the minimiser of J with the commands of A held at their bound (one backward
   pass with `clamped_gains`, then its linear plan, `linear_plan`);
3. du <- the best of clip(du + s (N - du)) over the step sizes s (J is cheap: one linear rollout);
4. stop when N lies in the box, the full step was the best and A did not change: du is then the
   minimiser over the box (KKT of the QP), and the law of step 2 has it as its plan.

The law returned has the feedback of the backward pass at the final A and the feedforward that
makes its linear plan du (`plan_feedforward`): its plan lies in the box for every step size
alpha in [0, 1] (alpha du, as the box contains 0), so clipping in the forward pass is a second-order
effect of the nonlinearity, and the line search's model is the model of a feasible plan.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._kernels.dense import matmul
from .._kernels.scan import packed_scan
from ..lqg.augmented import augmented_scan
from ..lqg.frame import SlotGains, acting_commands, slot_offsets, to_slots
from ..lqg.gains import clamped_gains
from ..lqg.model import DelayedLQG, merged_if_undelayed, stacked_dynamics
from ..lqg.structured import structured_slot_scan
from ..lqg.law import closed_loop_step
from .line_search import predicted_change

__all__ = ["linear_plan", "plan_feedforward", "model_cost", "bounded_step"]

# Projected Newton on the QP: iterations per backward pass of the solver, and the step sizes of its
# arc search, down to 1e-12: the projected arc is a descent path only for small enough steps, and J
# costs one linear rollout, so many are cheap (docs/derivation.md §15 on the solver's own, too few).
NEWTON_ITERATIONS = 60
STEP_SIZES = tuple(float(s) for s in 10.0 ** np.linspace(0.0, -12.0, 49))
_SEARCH, _FINAL, _DONE = 0, 1, 2     # the loop's stages: Newton iterations, the last backward pass, stop


def _closed_loop(lqg: DelayedLQG, feedback, data, law):
    """Scan the LQG's linear closed loop from dx_0 = 0, nothing pending, on y = [dx; pending] in the
    slot frame, with (du_k, out_k) = law(data_k, F_k, y_k); returns out [K, ...]."""
    l, nd, nx = lqg.frame_steps, lqg.n_controls, lqg.n_states
    merged = merged_if_undelayed(lqg)   # with a frame and l = 0, B1 = 0: du_delayed is then unused

    def step(y, row):
        slot, Z, F, data = row
        du, out = law(data, F, y)

        def plant(dx, du, du_delayed):
            du_delayed = jnp.zeros_like(du) if du_delayed is None else du_delayed
            return matmul(Z, jnp.concatenate([dx, du, du_delayed])), du, out

        # du is chosen already: the step applies it as a feedforward, without feedback
        return closed_loop_step(y, slot, SlotGains(du, jnp.zeros_like(F)), plant, nx, delay=delay)

    K = merged.horizon
    delay = None if lqg.delay_frame is None else lqg.delay_steps
    _, outs = packed_scan(step, jnp.zeros(nx + l * nd), (slot_offsets(K, l, nd), stacked_dynamics(merged),
                                                         feedback, data))
    return outs


def linear_plan(lqg: DelayedLQG, gains: SlotGains):
    """The law's plan on the LQG: du_k [K, d] of the linear closed loop with dx_0 = 0, nothing pending."""
    def law(I, F, y):
        du = I + matmul(F, y)
        return du, du

    return _closed_loop(lqg, gains.feedback, gains.feedforward, law)


def plan_feedforward(lqg: DelayedLQG, feedback, du):
    """The feedforward I [K, d] with which the law (``feedback`` [K, d, n + l d], slot frame) has the
    plan ``du`` [K, d]: I_k = du_k - F_k y_k along du's own linear trajectory y."""
    def law(du_k, F, y):
        return du_k, du_k - matmul(F, y)

    return _closed_loop(lqg, feedback, du, law)


def model_cost(lqg: DelayedLQG, du):
    """J(du) - J(0) of the LQG without noise for open-loop command deviations du [K, d], dx_0 = 0:
    sum_k 2 d'dx + dx'D dx + 2 e'du + du'E du + 2 du'N dx, plus the final 2 d_K'dx_K + dx_K'D_K dx_K
    (eq. 4), the state driven by A dx + B0 du_k + B1 du_{k-l} (eq. 3)."""
    acting = acting_commands(du, lqg.delay_steps, lqg.delay_frame is not None)

    def step(dx, row):
        A, B0, B1, u, ud = row
        return A @ dx + B0 @ u + B1 @ ud, dx

    dxK, dx = jax.lax.scan(step, jnp.zeros(lqg.n_states, du.dtype), (lqg.A, lqg.B0, lqg.B1, du, acting))
    return (2 * jnp.sum(dx * lqg.d[:-1]) + jnp.einsum("kn,knm,km->", dx, lqg.D[:-1], dx) + 2 * jnp.sum(du * lqg.e)
            + jnp.einsum("kd,kde,ke->", du, lqg.E, du) + 2 * jnp.einsum("kd,kdn,kn->", du, lqg.N, dx)
            + 2 * dxK @ lqg.d[-1] + dxK @ lqg.D[-1] @ dxK)


def bounded_step(lqg: DelayedLQG, reg, lower, upper, eps, method: str = "structured"):
    """The law whose plan minimises the LQG (without noise) over lower <= du <= upper [K, d].

    Args:
        lqg: the iteration's model (stored: the Newton iterations reuse it).
        reg: lambda, added to every H_k of the backward passes.
        lower, upper: [K, d] bounds on du (u_min - u_bar, u_max - u_bar; lower <= 0 <= upper).
        eps: [d] width of the epsilon-active set (``lqg.gains.margin_width``).
        method: "structured" or "augmented", the backward pass to use.

    Returns:
        (gains [slot frame], expected cost J(0) of the law under the LQG, ok, (a, b) of
        ``line_search.predicted_change``). ``ok`` is False where some H_k + lambda I restricted to
        the free commands was not positive definite (the gains are then non-finite).
    """
    K, n = lqg.horizon, lqg.n_states
    cost = lambda du: model_cost(lqg, du)
    gradient = jax.grad(cost)
    steps = jnp.asarray(STEP_SIZES)

    def gains_at(at_lower, at_upper):
        held = jnp.where(at_lower, lower, upper)
        fixed = at_lower | at_upper
        bounds = (jnp.where(fixed, held, -jnp.inf), jnp.where(fixed, held, jnp.inf))
        if method == "augmented":
            gains, value = augmented_scan(lqg, reg, gains_fn=clamped_gains, bounds=bounds)
            return to_slots(gains), value.positive_definite
        gains, _, ok = structured_slot_scan(lqg, reg, store_value=False, store_S=False, gains_fn=clamped_gains,
                                            bounds=bounds)
        return gains, ok

    def active(du):
        g = gradient(du)
        return (du <= lower + eps) & (g > 0), (du >= upper - eps) & (g < 0)

    def newton(carry):
        du, J, at_lower, at_upper, it, stage, _, _ = carry
        gains, ok = gains_at(at_lower, at_upper)
        point = linear_plan(lqg, gains)
        arc = jax.vmap(lambda s: jnp.clip(du + s * (point - du), lower, upper))(steps)
        J_arc = jax.vmap(cost)(arc)
        best = jnp.argmin(jnp.where(jnp.isfinite(J_arc), J_arc, jnp.inf))
        better = ok & (J_arc[best] < J) & (stage == _SEARCH)
        new_lower, new_upper = active(jnp.where(better, arc[best], du))
        inside = jnp.all((point >= lower) & (point <= upper))
        same = jnp.all(new_lower == at_lower) & jnp.all(new_upper == at_upper)
        # settled: du is the minimiser and these gains are its law; otherwise one more pass makes
        # the gains of the final active set
        stage = jnp.where(stage == _SEARCH,
                          jnp.where(better & ~(inside & (best == 0) & same),
                                    jnp.where(it + 1 < NEWTON_ITERATIONS, _SEARCH, _FINAL),
                                    jnp.where(same | ~better, _DONE, _FINAL)),
                          _DONE)
        return (jnp.where(better, arc[best], du), jnp.where(better, J_arc[best], J), new_lower, new_upper, it + 1,
                stage, gains, ok)

    du0 = jnp.zeros((K, lqg.n_controls), lower.dtype)
    empty = SlotGains(jnp.zeros_like(du0), jnp.zeros((K, lqg.n_controls, n + lqg.frame_steps * lqg.n_controls),
                                                     du0.dtype))
    carry = (du0, jnp.zeros((), du0.dtype), *active(du0), 0, jnp.asarray(_SEARCH), empty, jnp.asarray(True))
    du, _, _, _, _, _, gains, ok = jax.lax.while_loop(lambda c: c[5] != _DONE, newton, carry)
    gains = SlotGains(plan_feedforward(lqg, gains.feedback, du), gains.feedback)
    a, b = predicted_change(lqg, gains, jnp.zeros((K + 1, n, n), du.dtype))
    return gains, jnp.sum(lqg.d_tilde) + a + b, ok, (a, b)
