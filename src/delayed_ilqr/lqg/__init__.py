"""The delayed LQG problem of eq. (3)-(5) and its exact solutions: the public API.

The system, in deviations from a nominal trajectory (time-major arrays, k = 0..K-1):

    dx_{k+1} = A_k dx_k + B0_k du_k + B1_k du_{k-l} + sum_j xi_{k,j} (c_{k,j} + C0_{k,j} du_k + C1_{k,j} du_{k-l})
    cost_k   = d_tilde_k + 2 dx_k'd_k + dx_k'D_k dx_k + 2 du_k'e_k + du_k'E_k du_k + 2 du_k'N_k dx_k
    cost_K   = d_tilde_K + 2 dx_K'd_K + dx_K'D_K dx_K

Three solutions of the same problem:

* [`backward_pass`][delayed_ilqr.lqg.backward_pass]: Theorem 1 (eq. 6-8), the structured recursion on the value function (7),
  with the corrections of ``docs/derivation.md``. Per step it costs O(l^2 d^3 + l n^2 d + n^3).
* [`augmented_backward_pass`][delayed_ilqr.lqg.augmented_backward_pass]: the independent reference, a plain Riccati recursion on the
  augmented state z_k = [dx_k, du_{k-l}, ..., du_{k-1}]; per step O((n + l d)^3).
* [`policy_cost`][delayed_ilqr.lqg.policy_cost]: the exact expected cost of *any* affine delayed policy, by propagating the
  mean and second moment of z_k (no sampling; [`closed_loop_moments`][delayed_ilqr.lqg.closed_loop_moments] returns them);
  [`simulate_lqg`][delayed_ilqr.lqg.simulate_lqg] estimates it by Monte Carlo.

Both backward passes accept a Levenberg-Marquardt shift ``reg`` (the solver's lambda): the gains
use H + reg I, and the value function is the exact cost-to-go of the quadratic model under those
gains (see ``docs/derivation.md`` §4), so that J(0) is always the true cost of the returned policy.

Modules (the solver's internals are imported from them, not from here):

| module | contents |
|---|---|
| model | [`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG], the per-step `Stage`, ``StepModels``, Gains, Value |
| frame | the circular slot frame of the pending commands (``SlotGains``, conversions, per-channel acting components) |
| law | the delayed feedback law (6) and the closed-loop step every rollout runs |
| stage | one step of Theorem 1 as readable mathematics (the statement the fused step obeys) |
| gains | gain rules: unconstrained, box-constrained, unregularised feedback |
| boxqp | the box-constrained QP of the control-limited gain rule |
| r_update | the strategies that update the [l d, l d] block R |
| structured | the reverse scan with the fused step ([`backward_pass`][delayed_ilqr.lqg.backward_pass]) |
| augmented | the augmented-state reference ([`augmented_backward_pass`][delayed_ilqr.lqg.augmented_backward_pass]) |
| exact | [`policy_cost`][delayed_ilqr.lqg.policy_cost], [`closed_loop_moments`][delayed_ilqr.lqg.closed_loop_moments], [`simulate_lqg`][delayed_ilqr.lqg.simulate_lqg] |
| observation | [`DelayedObservation`][delayed_ilqr.lqg.DelayedObservation]: delayed, noisy sensors dy_k = H_k dx_{k-l_s} + G_k v_k |
| estimator | [`delayed_kalman`][delayed_ilqr.lqg.delayed_kalman]: the delayed Kalman filter without augmentation, and its run |
| output_feedback | [`separation_design`][delayed_ilqr.lqg.separation_design], [`output_feedback_cost`][delayed_ilqr.lqg.output_feedback_cost] (exact, any pair), [`separation_cost`][delayed_ilqr.lqg.separation_cost], [`simulate_output_feedback`][delayed_ilqr.lqg.simulate_output_feedback] |
| fusion | [`fused_kalman`][delayed_ilqr.lqg.fused_kalman]: several sensors with their own delays and periods, fused without augmentation; [`fused_estimates`][delayed_ilqr.lqg.fused_estimates], [`fused_design`][delayed_ilqr.lqg.fused_design] |
| jitter | a jittered input delay (the delay drawn at every step from a known distribution): [`jittered_backward_pass`][delayed_ilqr.lqg.jittered_backward_pass] (structured), [`jittered_augmented_pass`][delayed_ilqr.lqg.jittered_augmented_pass] (reference), [`jittered_policy_cost`][delayed_ilqr.lqg.jittered_policy_cost] (exact), [`simulate_jittered_lqg`][delayed_ilqr.lqg.simulate_jittered_lqg] |
| alternation | [`alternate`][delayed_ilqr.lqg.alternate]: Todorov's alternation of filter and controller for signal-dependent noise ([`filter_step`][delayed_ilqr.lqg.filter_step], [`controller_sweep`][delayed_ilqr.lqg.controller_sweep]) |
| fused_alternation | [`fused_alternate`][delayed_ilqr.lqg.fused_alternate]: the alternation with several sensors of different delays ([`fused_controller_sweep`][delayed_ilqr.lqg.fused_controller_sweep]) |

"""
from .augmented import augmented_backward_pass
from .exact import LQGRuns, Moments, closed_loop_moments, policy_cost, simulate_lqg
from .model import DelayedLQG, Gains, Value
from .observation import DelayedObservation
from .estimator import FilterCovariances, FilterGains, delayed_kalman, filter_estimates
from .output_feedback import (OutputFeedback, OutputFeedbackRuns, output_feedback_cost, separation_cost,
                              separation_design, simulate_output_feedback)
from .structured import backward_pass
from .jitter import jittered_augmented_pass, jittered_backward_pass, jittered_policy_cost, simulate_jittered_lqg
from .alternation import Alternation, alternate, controller_sweep, filter_step
from .fusion import (FusedFeedback, FusedLoop, FusionCovariances, FusionGains, fused_design, fused_estimates,
                     fused_kalman, fused_loop)
from .fused_alternation import FusedAlternation, fused_alternate, fused_controller_sweep

__all__ = [
    "DelayedLQG",
    "Gains",
    "Value",
    "LQGRuns",
    "backward_pass",
    "augmented_backward_pass",
    "policy_cost",
    "closed_loop_moments",
    "Moments",
    "simulate_lqg",
    "DelayedObservation",
    "FilterGains",
    "FilterCovariances",
    "delayed_kalman",
    "filter_estimates",
    "OutputFeedback",
    "OutputFeedbackRuns",
    "separation_design",
    "separation_cost",
    "output_feedback_cost",
    "simulate_output_feedback",
    "Alternation",
    "alternate",
    "controller_sweep",
    "filter_step",
    "FusionGains",
    "FusionCovariances",
    "FusedFeedback",
    "fused_kalman",
    "fused_estimates",
    "fused_design",
    "FusedLoop",
    "fused_loop",
    "jittered_backward_pass",
    "jittered_augmented_pass",
    "jittered_policy_cost",
    "simulate_jittered_lqg",
    "FusedAlternation",
    "fused_alternate",
    "fused_controller_sweep",
]
