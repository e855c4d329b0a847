"""One input delay per command channel (``delay_steps=[l_1, ..., l_d]``, docs/derivation.md §18):
channel j's column of B1, C1 acts with du_{k-l_j}.

References, independent of the structured pass: the state-augmentation pass over the same
channels (``lqg.augmented_backward_pass``), whose augmented matrices are checked here against a
construction written out channel by channel; the library's single-delay pass where every channel
has the same delay; and the exact second moments of the closed loop (``lqg.policy_cost``).
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr import lqg as _lqg
from delayed_ilqr.lqg import DelayedLQG
from delayed_ilqr.lqg.augmented import augment

from comparisons import WorstDifference, rel_err   # tests/comparisons.py
from test_lqg import random_arrays                  # tests/test_lqg.py

RTOL = 1e-9
_WORST = WorstDifference("test_channels: worst per-channel structured-vs-reference relative difference")
_report_worst = _WORST.fixture()

# (K, n, d, p, L): per-channel delays 0..L are drawn; each shape compiles each pass once (the
# delays are data). The second has L >= K: channels whose commands never act in the horizon.
SHAPES = [(6, 2, 3, 2, 4), (4, 3, 2, 1, 5)]


def _channel_delays(data, d: int, L: int):
    """Delays 0..L per channel, the longest equal to L (the frame is max_j l_j)."""
    delays = data.draw(st.lists(st.integers(0, L), min_size=d, max_size=d), label="delays")
    delays[data.draw(st.integers(0, d - 1), label="longest")] = L
    return delays


def _errors(gains, value, ref_gains, ref_value):
    errs = {f: rel_err(getattr(gains, f), getattr(ref_gains, f))
            for f in ("feedforward", "state_feedback", "delay_feedback")}
    errs.update({f: rel_err(getattr(value, f), getattr(ref_value, f)) for f in ("s_tilde", "s", "S", "r", "Rt", "R")})
    return errs


@settings(max_examples=12, deadline=None)
@given(shape=st.sampled_from(SHAPES), data=st.data(), seed=st.integers(0, 2 ** 31 - 1),
       reg=st.sampled_from([0.0, 0.3]))
def test_per_channel_pass_equals_augmentation(shape, data, seed, reg):
    """Random time-varying data and random channel delays (0, 1, equal, l >= K among them): every
    gain and value block of the structured pass equals the augmented pass's to round-off, and
    J(0) is the exact expected cost of the returned policy."""
    K, n, d, p, L = shape
    delays = _channel_delays(data, d, L)
    lqg = DelayedLQG(**random_arrays(seed, K, n, d, p, delays))
    gains, value = _lqg.backward_pass(lqg, reg)
    ref_gains, ref_value = _lqg.augmented_backward_pass(lqg, reg)
    assert bool(value.positive_definite) and bool(ref_value.positive_definite)
    errs = _errors(gains, value, ref_gains, ref_value)
    errs["policy_cost"] = rel_err(_lqg.policy_cost(lqg, gains), value.expected_cost)
    worst = max(errs, key=errs.get)
    _WORST.record(errs[worst], f"{worst}, K={K} n={n} d={d} p={p} delays={delays} reg={reg}")
    assert all(e <= RTOL for e in errs.values()), (delays, errs)
    # a channel's entries older than its delay belong to commands that have acted: exactly zero
    M = np.asarray(gains.delay_feedback)
    for j, l_j in enumerate(delays):
        assert not np.any(M[:, :L - l_j, :, j]), (j, l_j)


@pytest.mark.parametrize("l", [0, 1, 3])
def test_equal_channel_delays_are_the_single_delay(l):
    """Every channel delayed by l: the per-channel pass (a frame of l slots, l as data per channel)
    gives the single-delay pass's gains and value to round-off."""
    K, n, d, p = 6, 2, 3, 2
    arrays = random_arrays(11 + l, K, n, d, p, l)
    single = _lqg.backward_pass(DelayedLQG(**arrays), 0.0)
    per_channel = _lqg.backward_pass(DelayedLQG(**{**arrays, "delay_steps": [l] * d}), 0.0)
    errs = _errors(*per_channel, *single)
    _WORST.record(max(errs.values()), f"equal delays l={l}")
    assert all(e <= RTOL for e in errs.values()), errs


def _augmented_by_channel(arrays, delays):
    """The augmented system written out entry by entry: z_k = [dx_k, du_{k-L}, ..., du_{k-1}],
    channel j of B1, C1 reading the buffer's entry L - l_j (du_k itself for l_j = 0)."""
    A, B0, B1, C0, C1 = (np.asarray(arrays[f]) for f in ("A", "B0", "B1", "C0", "C1"))
    K, n, d = B0.shape
    p, L = C0.shape[1], max(delays)
    m = n + L * d
    Az, Bz = np.zeros((K, m, m)), np.zeros((K, m, d))
    Cz, Cu = np.zeros((K, p, m, m)), np.zeros((K, p, m, d))
    Az[:, :n, :n], Bz[:, :n], Cu[:, :, :n] = A, B0, C0
    for j, l_j in enumerate(delays):
        if l_j == 0:
            Bz[:, :n, j] += B1[:, :, j]
            Cu[:, :, :n, j] += C1[:, :, :, j]
        else:
            column = n + (L - l_j) * d + j
            Az[:, :n, column] = B1[:, :, j]
            Cz[:, :, :n, column] = C1[:, :, :, j]
    for i in range(L - 1):                   # the buffer moves up one entry
        Az[:, n + i * d:n + (i + 1) * d, n + (i + 1) * d:n + (i + 2) * d] = np.eye(d)
    if L:
        Bz[:, m - d:] = np.eye(d)            # du_k enters last
    return Az, Bz, Cz, Cu


@pytest.mark.parametrize("delays", [[0, 2, 1], [3, 3, 0], [1, 0, 0]])
def test_augmentation_reads_each_channel_at_its_delay(delays):
    """The reference's augmented matrices equal the construction written out channel by channel."""
    arrays = random_arrays(5, 4, 2, 3, 2, delays)
    aug = augment(DelayedLQG(**arrays))
    for name, ref in zip(("Az", "Bz", "Cz", "Cu"), _augmented_by_channel(arrays, delays)):
        np.testing.assert_array_equal(np.asarray(aug[name]), ref, err_msg=name)
