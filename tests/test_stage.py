"""The readable step of Theorem 1 (``lqg.stage.stage_step``) is the recursion the library runs.

Step by step, the fused structured pass (slot frame, fused products, R-update strategies) equals
``stage_step`` applied to its own J(k+1): the gains I, L, M and every block of J(k). And
``stage_step`` iterated from J(K) equals the augmented-state reference, so the readable
mathematics is checked against an independent derivation too.
"""
from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr.lqg import DelayedLQG, augmented_backward_pass, backward_pass
from delayed_ilqr.lqg.model import Stage
from delayed_ilqr.lqg.stage import CostToGo, stage_step
from delayed_ilqr.lqg.structured import structured_scan
from comparisons import rel_err
from test_lqg import random_arrays

STEP_RTOL = 1e-10              # one step from the same J(k+1): round-off only
RECURSION_RTOL = 1e-9          # K steps from J(K), as tests/test_lqg.py's RTOL
GAIN_FIELDS = ("feedforward", "state_feedback", "delay_feedback")

_step = jax.jit(stage_step)


def _stage(lqg: DelayedLQG, k: int) -> Stage:
    return Stage(*(getattr(lqg, f)[k] for f in Stage._fields))


def _cost_to_go(value, k: int) -> CostToGo:
    return CostToGo(*(getattr(value, f)[k] for f in CostToGo._fields))


def _final(lqg: DelayedLQG) -> CostToGo:
    n, nd, l = lqg.n_states, lqg.n_controls, lqg.delay_steps
    z = np.zeros
    return CostToGo(lqg.d_tilde[-1], lqg.d[-1], lqg.D[-1], z((l, nd)), z((l, n, nd)), z((l, l, nd, nd)))


def _assert_close(got, want, rtol, what):
    err = rel_err(got, want)
    assert err <= rtol, (what, err)


# Each distinct (K, n, d, p, l) compiles the passes and the step (about a second each on 2 cores),
# so shapes come from a pool, shared with tests/test_lqg.py's, that covers n, d in 1..4, p in 0..4
# (p = 0: no noise), l in {0, 1, 2, 3, 5} and l >= K; hypothesis draws the data and reg.
SHAPES = [  # (K, n, d, p, l)
    (1, 2, 2, 2, 2),      # one step, delayed: only gains on commands sent before t = 0
    (3, 3, 2, 2, 1),
    (6, 2, 3, 1, 9),      # l >= K: no command sent inside the horizon ever acts
    (6, 4, 3, 2, 0),      # undelayed
    (8, 1, 2, 4, 5),
    (8, 3, 2, 0, 3),      # deterministic
]
_ids = lambda s: "K{}-n{}-d{}-p{}-l{}".format(*s)


@st.composite
def cases(draw):
    """Random data for a shape, with and without a regularisation reg."""
    kw = dict(cross=draw(st.booleans()), mult_noise=draw(st.sampled_from([0.0, 0.5])))
    return draw(st.integers(0, 2**31 - 1)), kw, draw(st.sampled_from([0.0, 0.5]))


@pytest.mark.parametrize("shape", SHAPES, ids=_ids)
@settings(max_examples=3, deadline=None)
@given(case=cases())
def test_fused_step_equals_readable_step(shape, case):
    """At every k: stage_step(stage k, J(k+1) of the fused pass) == the fused pass's gains at k and J(k)."""
    seed, kw, reg = case
    lqg = DelayedLQG(**random_arrays(seed, *shape, **kw))
    gains, value = backward_pass(lqg, reg)
    for k in range(lqg.horizon):
        got, J = _step(_stage(lqg, k), _cost_to_go(value, k + 1), reg)
        assert bool(got.ok)
        for f in GAIN_FIELDS:
            _assert_close(getattr(got, f), getattr(gains, f)[k], STEP_RTOL, (k, f))
        for f in CostToGo._fields:
            _assert_close(getattr(J, f), getattr(value, f)[k], STEP_RTOL, (k, f))


@pytest.mark.parametrize("shape", SHAPES, ids=_ids)
@settings(max_examples=2, deadline=None)
@given(case=cases())
def test_readable_recursion_equals_augmentation(shape, case):
    """stage_step iterated from J(K) to J(0) == the Riccati recursion on the augmented state."""
    seed, kw, reg = case
    lqg = DelayedLQG(**random_arrays(seed, *shape, **kw))
    gains, value = augmented_backward_pass(lqg, reg)
    J = _final(lqg)
    for k in reversed(range(lqg.horizon)):
        got, J = _step(_stage(lqg, k), J, reg)
        for f in GAIN_FIELDS:
            _assert_close(getattr(got, f), getattr(gains, f)[k], RECURSION_RTOL, (k, f))
        for f in CostToGo._fields:
            _assert_close(getattr(J, f), getattr(value, f)[k], RECURSION_RTOL, (k, f))


@pytest.mark.parametrize("block", [1, 3])
def test_every_r_update_strategy_is_the_readable_step(block):
    """The deferred (block 3) and copied-factor (l d >= 64) strategies, on a problem long enough for
    slots to be replaced several times: each step still equals stage_step."""
    lqg = DelayedLQG(**random_arrays(5, 12, 2, 2, 1, 33))                  # l d = 66
    gains, out, ok = jax.jit(lambda q: structured_scan(q, 0.2, store_value=True, block=block))(lqg)
    assert bool(ok)
    final = _final(lqg)
    for k in range(lqg.horizon):
        nxt = final if k + 1 == lqg.horizon else CostToGo(*(o[k + 1] for o in out))
        got, J = _step(_stage(lqg, k), nxt, 0.2)
        for f in GAIN_FIELDS:
            _assert_close(getattr(got, f), getattr(gains, f)[k], STEP_RTOL, (k, f))
        for f, want in zip(CostToGo._fields, out):
            _assert_close(getattr(J, f), want[k], STEP_RTOL, (k, f))
