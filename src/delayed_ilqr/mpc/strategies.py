"""How each compensation of the input delay turns the tick's data into the problem it solves.

Every strategy is the same controller (one solver, one tick): they differ only in the tick
problem's model delay, the state it starts from, the time it starts at and which of the plan's
commands is sent. With l_c the controller's delay (the problem's l, plus one when the solve time
is charged) and b = [u_{k-l_c}, ..., u_{k-1}] the commands sent and not yet acting:

| compensation | model delay | start state | start t | steps | command sent |
|---|---|---|---|---|---|
| none | 0 | x_k | t_k | K | plan[0] |
| predict | 0 | x_hat_{k+l_c} = model(x_k; b) | t_{k+l} | K - l_c | plan[0] |
| replay (sent) | l_c | x_k, then b acts | t_k | K | plan[0] |
| replay (planned) | 0 | x_k | t_k | K | plan[l_c] |
| inflight | l_c | x_k, then b acts (M_k^i on b) | t_k | K | plan[0] |

Every horizon ends at t_{k+K}: the one of ``predict`` starts where the prediction ends.

* none: solves as if the plant had no delay and applies the result to the delayed plant.
* predict (acados' advice, a Smith predictor): rolls the model forward over the latency with the
  commands in flight, then solves the delay-free problem from the prediction. On a deterministic
  model this is the problem ``inflight`` solves, less its first l_c steps, whose states are fixed
  by the commands in flight (their cost is a constant) and whose last l_c commands act after the
  horizon (zero at the optimum): iterated to convergence the two send the same commands.
* replay (Nav2's MPPI): the optimiser plans the commands that *act* from now, v_0..v_{K-1}, and
  sends v_{l_c}. With ``replay_history="sent"`` (Nav2's command-history replay) the first l_c are
  the commands sent, replayed through the model: this is exactly the tick problem of ``inflight``
  (same states, same costs, same decision variables), so the two send the same commands; at
  convergence on a deterministic model both also send what ``predict`` sends up to the horizon's
  end. With ``replay_history="planned"`` (Nav2's first ``model_delay``: the command vector shifted)
  the optimiser re-plans v_0..v_{l_c-1} too, as if the commands in flight could still change:
  the prediction replays the plan's own values, not the ones that were sent.

Predict, replay (sent) and inflight thus differ only before convergence (the real-time iteration's
single step is taken on different linearisations: the prediction's versus the whole horizon's),
with signal-dependent noise (the delayed LQG weighs the noise of the commands in flight) and in
the tick's law ([`TickLaw`][delayed_ilqr.mpc.TickLaw]: inflight's M feeds back commands in flight
that differ from their plan). For linear dynamics and quadratic costs the delayed LQR law
u = L x + sum_i M^i u_{k+i-l} is the predictor's law written on the commands in flight.
* inflight (this library): the delayed problem with the commands in flight as known inputs; the
  backward pass gives the law du_j = I_j + L_j dx_j + sum_i M_j^i du_{j+i-l_c}, whose M feeds back
  the commands in flight (the tick's law, and the solver's rollouts within the horizon).
"""
from __future__ import annotations

from typing import NamedTuple

__all__ = ["COMPENSATIONS", "REPLAY_HISTORIES", "Strategy", "strategy"]

COMPENSATIONS = ("inflight", "none", "predict", "replay")
REPLAY_HISTORIES = ("sent", "planned")


class Strategy(NamedTuple):
    """The static shape of a compensation for a controller delay l_c (module docstring's table)."""

    model_delay: int        # the tick problem's delay_steps
    predict_steps: int      # steps of the model from x_k before the solve
    send_index: int         # the plan's command that is sent
    horizon: int            # the tick problem's horizon


def strategy(compensation: str, controller_delay: int, horizon: int, replay_history: str = "sent") -> Strategy:
    """The [`Strategy`][delayed_ilqr.mpc.strategies.Strategy] of ``compensation`` for the controller delay l_c and horizon K."""
    l = controller_delay
    if compensation == "none":
        return Strategy(0, 0, 0, horizon)
    if compensation == "predict":
        return Strategy(0, l, 0, horizon - l)
    if compensation == "replay" and replay_history == "planned":
        return Strategy(0, 0, l, horizon)
    return Strategy(l, 0, 0, horizon)        # inflight, and replay of the sent history
