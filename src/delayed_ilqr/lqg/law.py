"""The closed loop under the delayed feedback law (eq. 6), written once:

    du_k = I_k + L_k dx_k + sum_i M_k^i du_{k+i-l}

`delayed_law` is the law on the augmented deviation z_k = [dx_k; pending_k], whose pending
part lists the commands already sent but not yet acting in the order of the feedback's columns;
the law itself does not know that order. Two orders are in use:

* the slot frame of the backward recursion (`SlotGains`): du_j sits in
  slot j mod l of the flat [l d] pending vector. Step k reads slot k mod l (du_{k-l}, the command
  that starts acting) and writes du_k into it, so a closed loop never shifts a buffer;
* time order ([`Gains`][delayed_ilqr.lqg.Gains] and the augmented state of ``lqg.augment``):
  pending = [du_{k-l}, ..., du_{k-1}]; `augmented_feedback` lays [L, M] out in that order.

`closed_loop_step` advances y = [x, pending] one step in the slot frame, with the plant
given as a function of the command deviation. It is the step of the solver's rollouts and line
search (``candidates.nonlinear_step``: the nonlinear plant around a nominal) and of the line
search's model (``line_search.predicted_change``: the LQG's linear dynamics). The Monte Carlo
``delayed_ilqr.simulate`` runs a policy whose delay may differ from the plant's, with the pending
commands in time order (faster under its vmap over trials): it applies `delayed_law` with
`augmented_feedback`. The exact policy cost propagates moments of z instead of samples: it
uses the law's affine form (`augmented_feedback`, `closed_loop_affine`).

The law is an object of the LQG layer: this module depends on nothing but the fused products and the
slot frame, and the solver's loops (``ilqg``) import it from here.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import jax
import jax.numpy as jnp

from .._kernels.dense import matmul
from .frame import acting_offset, take_acting

if TYPE_CHECKING:
    from .frame import SlotGains
    from .model import Gains

__all__ = ["delayed_law", "write_slot", "closed_loop_step", "augmented_feedback", "closed_loop_affine"]


def delayed_law(feedforward, feedback, z):
    """Eq. (6): du_k = I_k + [L_k, M_k] z_k.

    Args:
        feedforward: [d] I_k (alpha I_k in a line search, zero when a policy runs without it).
        feedback: [d, n + l d] [L_k, M_k], M_k's columns in the order of z's pending part.
        z: [n + l d] the augmented deviation [dx_k; pending_k].

    Returns:
        du_k [d].
    """
    return feedforward + matmul(feedback, z)


def write_slot(frame, offset, value):
    """``frame`` with ``value`` [d] at ``offset`` (du_k replaces du_{k-l}, which now acts)."""
    return jax.lax.dynamic_update_slice_in_dim(frame, value, offset, 0)


def closed_loop_step(y, slot, gains: SlotGains, plant: Callable, n_states: int, x_bar=None, delay=None):
    """Step k -> k+1 of the closed loop on y = [x; pending] in the slot frame.

    Args:
        y: [n + l d] the state x_k and the pending deviations (du_j in slot j mod l); l = 0 allowed.
        slot: (k mod l) d, the offset of du_{k-l} in pending, where du_k is written (0 for l = 0).
        delay: with a frame of L slots and the delay as data (``delay_frame``), the traced l:
            du_{k-l} is read at slot (k - l) mod L and du_k written at ``slot`` = (k mod L) d;
            None: du_{k-l} is at ``slot``. For a framed l = 0 the slot read holds a command that
            has acted: the plant must use du instead. Per-channel delays ([d]): component j of
            du_delayed is read from slot (k - l_j) mod L.
        gains: row k of `SlotGains`: feedforward [d], feedback [d, n + l d].
        plant: ``plant(x, du, du_delayed) -> (x_new, du_sent, out)``, the plant's step under the
            command deviation du_k, with du_delayed = du_{k-l} [d] (None for l = 0); du_sent is the
            deviation the frame keeps for step k (after clipping, say); ``out`` comes back as is.
        n_states: n.
        x_bar: [n] the nominal state (dx = x - x_bar); None when x is already the deviation.

    Returns:
        (y_{k+1}, out).
    """
    nx, nd = n_states, gains.feedforward.shape[-1]
    delayed = y.shape[-1] > nx
    x = y[:nx]
    z = y if x_bar is None else jnp.concatenate([x - x_bar, y[nx:]])
    du = delayed_law(gains.feedforward, gains.feedback, z)
    acting = slot if delay is None or not delayed else acting_offset(slot, delay, (y.shape[-1] - nx) // nd, nd)
    x_new, du_sent, out = plant(x, du, take_acting(y, nx + acting, nd) if delayed else None)
    y_new = jnp.concatenate([x_new, y[nx:]])
    if delayed:
        y_new = write_slot(y_new, nx + slot, du_sent)
    return y_new, out


def augmented_feedback(gains: Gains):
    """[L_k, M_k^0, ..., M_k^{l-1}] [K, d, n + l d]: the law's feedback on the time-ordered
    augmented state z_k = [dx_k, du_{k-l}, ..., du_{k-1}] of ``lqg.augment``."""
    K, nd = gains.feedforward.shape
    return jnp.concatenate([gains.state_feedback, jnp.moveaxis(gains.delay_feedback, 1, 2).reshape(K, nd, -1)],
                           axis=2)


def closed_loop_affine(Mz, Mu, feedforward, feedback):
    """The law substituted into a map Mz z + Mu du of the augmented state: (Mz + Mu F, Mu I), so
    that the map is (Mz + Mu F) z + Mu I. Mz [..., m, N], Mu [..., m, d] (the dynamics Az, Bz, or
    the noise columns Cz, Cu with a leading [p]); feedforward [d], feedback [d, N] in z's order."""
    return Mz + Mu @ feedback, Mu @ feedforward
