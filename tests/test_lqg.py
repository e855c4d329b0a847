"""Tests of the delayed LQG layer (``delayed_ilqr.lqg``).

Every exactness test compares against something computed a different way: the state
augmentation Riccati recursion, a dense QP over the whole control sequence, the exact expected
cost of a policy (second-moment propagation), or Monte Carlo. A test-local numpy copy of the
recursion shows that the paper's printed formulas (errata E1, E3/E4, E5) fail these checks.
"""
from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr import lqg as _lqg
from delayed_ilqr.ilqg.line_search import predicted_change
from delayed_ilqr.lqg import DelayedLQG, Gains, policy_cost, simulate_lqg
from delayed_ilqr.lqg.frame import from_slots, to_slots
from delayed_ilqr.lqg.gains import unconstrained_gains
from delayed_ilqr.lqg.structured import structured_scan, structured_slot_scan

from comparisons import WorstDifference, rel_err   # tests/comparisons.py

RTOL = 1e-9
GAIN_FIELDS = ("feedforward", "state_feedback", "delay_feedback")
VALUE_FIELDS = ("s_tilde", "s", "S", "r", "Rt", "R")

# Worst structured-vs-augmented relative difference seen in this module (printed at the end).
_WORST = WorstDifference("test_lqg: worst structured-vs-augmented relative difference")
_report_worst = _WORST.fixture()


# ---------------------------------------------------------------------------------------------
# Problem generation
# ---------------------------------------------------------------------------------------------

def backward_pass(lqg, reg=0.0):
    """The library's pass, always called the same way: jit caches positional, keyword and
    defaulted ``reg`` separately, and each compilation costs about a second."""
    return _lqg.backward_pass(lqg, float(reg))


def augmented_backward_pass(lqg, reg=0.0):
    return _lqg.augmented_backward_pass(lqg, float(reg))


def random_arrays(seed, K, n, d, p, l, *, b0_zero=False, noise=1.0, mult_noise=0.3, cross=True,
                  singular_state_cost=False):
    """Random time-varying data of a convex delayed LQG, as a dict of DelayedLQG arguments.

    The stage cost is [dx; du; 1]' W_k [dx; du; 1] with W_k PSD, so E is SPD, D PSD and the cross
    term N is whatever keeps the joint quadratic convex; the + 0.1 on the constant makes every
    stage cost >= 0.1, so J(0) >= 0.1 (K + 1) and relative comparisons are well conditioned.
    """
    rng = np.random.default_rng(seed)
    m = n + d + 1
    X = rng.standard_normal((K + 1, m, m if not singular_state_cost else 1))
    W = X @ np.swapaxes(X, 1, 2) / m
    W += np.diag(np.r_[np.full(n, 0.0 if singular_state_cost else 0.1), np.full(d, 0.1), 0.1])
    A = 0.8 * np.eye(n) + 0.4 * rng.standard_normal((K, n, n)) / np.sqrt(n)
    B0 = np.zeros((K, n, d)) if b0_zero else rng.standard_normal((K, n, d)) / np.sqrt(n)
    B1 = rng.standard_normal((K, n, d)) / np.sqrt(n)
    return dict(
        A=A, B0=B0, B1=B1,
        c=noise * 0.3 * rng.standard_normal((K, p, n)),
        C0=mult_noise * rng.standard_normal((K, p, n, d)),
        C1=mult_noise * rng.standard_normal((K, p, n, d)),
        d_tilde=W[:, -1, -1], d=W[:, :n, -1], D=W[:, :n, :n],
        e=W[:-1, n:n + d, -1], E=W[:-1, n:n + d, n:n + d],
        N=W[:-1, n:n + d, :n] if cross else np.zeros((K, d, n)),
        delay_steps=l)


def random_lqg(seed, K, n, d, p, l, **kw) -> DelayedLQG:
    return DelayedLQG(**random_arrays(seed, K, n, d, p, l, **kw))



def structured_vs_augmented(lqg, reg=0.0, label=""):
    """Asserts that all gains, all value blocks and J(0) of both passes agree to RTOL."""
    gs, vs = backward_pass(lqg, reg)
    ga, va = augmented_backward_pass(lqg, reg)
    errs = {f: rel_err(getattr(gs, f), getattr(ga, f)) for f in GAIN_FIELDS}
    errs.update({f: rel_err(getattr(vs, f), getattr(va, f)) for f in VALUE_FIELDS})
    errs["J0"] = rel_err(vs.expected_cost, va.expected_cost)
    worst = max(errs, key=errs.get)
    _WORST.record(errs[worst], f"{worst}, {label or repr(lqg)}, reg={reg}")
    assert bool(vs.positive_definite) and bool(va.positive_definite)
    assert all(e <= RTOL for e in errs.values()), errs
    return gs, vs


# ---------------------------------------------------------------------------------------------
# Structured (Theorem 1, corrected) == state augmentation
# ---------------------------------------------------------------------------------------------

# Each distinct (K, n, d, p, l) recompiles both passes (about a second each), so shapes come from
# a fixed pool that covers n, d in 1..4, p in 0..4, l in {0, 1, 2, 3, 5, 9}, K in 1..30, l >= K
# and l < K; every shape is run, and hypothesis draws the data, B0 = 0, the cross term, a singular
# D, multiplicative noise and reg for each. Several pool shapes are shared with the fixed tests
# below, so their compilations are reused.
SHAPES = [  # (K, n, d, p, l)
    (1, 1, 1, 0, 0),      # one step, undelayed, deterministic
    (1, 2, 2, 2, 2),      # one step, delayed: only gains on commands sent before t = 0
    (3, 3, 2, 2, 1),      # l = 1
    (5, 4, 4, 3, 2),
    (6, 2, 3, 1, 9),      # l >= K: no command sent inside the horizon ever acts
    (6, 4, 3, 2, 0),      # undelayed with noise
    (8, 1, 2, 4, 5),
    (8, 3, 2, 0, 3),      # deterministic
    (12, 3, 2, 2, 3),
    (30, 2, 1, 1, 5),     # longer horizon
]


@st.composite
def options(draw):
    opts = dict(b0_zero=draw(st.booleans()), cross=draw(st.booleans()),
                singular_state_cost=draw(st.booleans()), mult_noise=draw(st.sampled_from([0.0, 0.5])))
    reg = draw(st.sampled_from([0.0, 0.0, 0.5]))
    seed = draw(st.integers(0, 2**31 - 1))
    return seed, opts, reg


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "K{}-n{}-d{}-p{}-l{}".format(*s))
@settings(max_examples=5)           # per shape: 50 examples in all, but only 10 compilations
@given(case=options())
def test_structured_matches_augmentation(shape, case):
    seed, opts, reg = case
    lqg = random_lqg(seed, *shape, **opts)
    _, vs = structured_vs_augmented(lqg, reg, label=f"{lqg!r} {opts}")
    # Blocks for commands that never act (k + i >= K) are exactly zero.
    K, l = lqg.horizon, lqg.delay_steps
    r, Rt, R = np.asarray(vs.r), np.asarray(vs.Rt), np.asarray(vs.R)
    for k in range(K + 1):
        dead = slice(max(K - k, 0), l)
        assert not np.any(r[k, dead]) and not np.any(Rt[k, dead])
        assert not np.any(R[k, dead]) and not np.any(R[k, :, dead])


@pytest.mark.parametrize("K, d, l", [(50, 1, 300), (100, 1, 60), (60, 2, 40)])
def test_long_delay_matches_augmentation(K, d, l):
    """l >= K and l < K with long delays; l d = 300 runs the default blocked pass (block 16), and
    from l d = 64 on the R update reads its factors copied out of the value update's product."""
    structured_vs_augmented(random_lqg(7, K, 2, d, 1, l), label=f"K={K}, d={d}, l={l}")


@pytest.mark.parametrize("shape", [SHAPES[i] for i in (2, 4, 8, 9)], ids=lambda s: "K{}-n{}-d{}-p{}-l{}".format(*s))
@pytest.mark.parametrize("block", [2, 7])
@settings(max_examples=3)
@given(case=options())
def test_blocked_pass_matches_augmentation(shape, block, case):
    """The pass with the O((l d)^2) update deferred to one product per block of q steps
    (``structured_scan(block=q)``, the default for l d >= 300) equals augmentation, including
    horizons that are not a multiple of q (padded) and l >= K."""
    seed, opts, reg = case
    lqg = random_lqg(seed, *shape, **opts)
    scan = jax.jit(lambda q, reg: structured_scan(q, reg, store_value=True, block=block))
    gains, out, ok = scan(lqg, float(reg))
    ga, va = augmented_backward_pass(lqg, reg)
    assert bool(ok)
    for got, want in zip(gains, ga):
        assert rel_err(got, want) <= RTOL
    for got, want in zip(out, (va.s_tilde, va.s, va.S, va.r, va.Rt, va.R)):
        assert rel_err(got, want[:-1]) <= RTOL


def test_undelayed_equals_merged_inputs():
    """l = 0: B1/C1 act on du_k, so the problem equals one with B0 + B1, C0 + C1 and no B1."""
    a = random_arrays(3, 6, 4, 3, 2, 0)
    merged = dict(a, B0=a["B0"] + a["B1"], B1=np.zeros_like(a["B1"]),
                  C0=a["C0"] + a["C1"], C1=np.zeros_like(a["C1"]))
    g1, v1 = backward_pass(DelayedLQG(**a))
    g2, v2 = backward_pass(DelayedLQG(**merged))
    assert rel_err(v1.expected_cost, v2.expected_cost) <= RTOL
    assert rel_err(g1.state_feedback, g2.state_feedback) <= RTOL


# ---------------------------------------------------------------------------------------------
# Deterministic case: the dense QP over the whole control sequence
# ---------------------------------------------------------------------------------------------

def dense_qp(a):
    """min over du_0..du_{K-1} of the noise-free cost, by the normal equations (numpy only)."""
    A, B0, B1, l = a["A"], a["B0"], a["B1"], a["delay_steps"]
    K, n, d = B0.shape
    X = [np.zeros((n, K * d))]                        # dx_k = X[k] @ u, u = all du stacked
    for k in range(K):
        nxt = A[k] @ X[k]
        nxt[:, k * d:(k + 1) * d] += B0[k]
        if k - l >= 0:                                # du_{k-l} = 0 for k < l
            nxt[:, (k - l) * d:(k - l + 1) * d] += B1[k]
        X.append(nxt)
    Q = np.zeros((K * d, K * d))
    b = np.zeros(K * d)
    const = float(np.sum(a["d_tilde"]))
    for k in range(K + 1):
        Q += X[k].T @ a["D"][k] @ X[k]
        b += X[k].T @ a["d"][k]
        if k < K:
            P = np.zeros((d, K * d))
            P[:, k * d:(k + 1) * d] = np.eye(d)
            cross = P.T @ a["N"][k] @ X[k]
            Q += P.T @ a["E"][k] @ P + cross + cross.T
            b += P.T @ a["e"][k]
    u = -np.linalg.solve(Q, b)
    return const + b @ u, u.reshape(K, d)


@pytest.mark.parametrize("K, n, d, l, b0_zero", [
    (8, 3, 2, 3, False), (8, 3, 2, 3, True), (5, 2, 2, 7, False), (6, 3, 1, 0, False)])
def test_deterministic_optimum_equals_dense_qp(K, n, d, l, b0_zero):
    a = random_arrays(11, K, n, d, 0, l, b0_zero=b0_zero)
    lqg = DelayedLQG(**a)
    gains, value = backward_pass(lqg)
    j_qp, u_qp = dense_qp(a)
    assert rel_err(value.expected_cost, j_qp) <= RTOL
    runs = simulate_lqg(lqg, gains, n_trials=1)       # p = 0: the closed loop is deterministic
    assert rel_err(runs.du[0], u_qp) <= 1e-8
    assert rel_err(runs.cost[0], j_qp) <= RTOL


# ---------------------------------------------------------------------------------------------
# Optimality among affine delayed policies, and the exact policy cost
# ---------------------------------------------------------------------------------------------

def _perturb(gains, rng, which, scale):
    out = {}
    for f in GAIN_FIELDS:
        g = np.asarray(getattr(gains, f))
        out[f] = g + scale * rng.standard_normal(g.shape) if f in which else g
    return Gains(**out)


@pytest.mark.parametrize("seed, K, n, d, p, l", [(21, 12, 3, 2, 2, 3), (22, 6, 2, 3, 1, 9)])
def test_perturbed_gains_never_cost_less(seed, K, n, d, p, l):
    """Both signs of each random direction: a nonzero gradient would make one of them cheaper."""
    lqg = random_lqg(seed, K, n, d, p, l, mult_noise=0.5)
    gains, value = backward_pass(lqg)
    j_opt = float(policy_cost(lqg, gains))
    assert rel_err(j_opt, value.expected_cost) <= RTOL
    rng = np.random.default_rng(seed)
    for which in (("feedforward",), ("state_feedback",), ("delay_feedback",), GAIN_FIELDS):
        for scale in (1e-3, 1e-1, 1.0):
            direction = int(rng.integers(2**31))
            for sign in (1.0, -1.0):
                perturbed = _perturb(gains, np.random.default_rng(direction), which, sign * scale)
                j = float(policy_cost(lqg, perturbed))
                assert j >= j_opt * (1 - 1e-12), (which, scale, sign, j, j_opt)
                if "feedforward" in which:             # H is PD: moving I always costs more
                    assert j > j_opt, (which, scale, sign, j, j_opt)


# ---------------------------------------------------------------------------------------------
# Monte Carlo
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("suboptimal", [False, True])
def test_monte_carlo_matches_policy_cost(suboptimal):
    lqg = random_lqg(31, 12, 3, 2, 2, 3, mult_noise=0.5)
    gains, _ = backward_pass(lqg)
    if suboptimal:
        gains = _perturb(gains, np.random.default_rng(5), GAIN_FIELDS, 0.3)
    exact = float(policy_cost(lqg, gains))
    cost = np.asarray(simulate_lqg(lqg, gains, n_trials=20000, seed=123).cost)
    se = cost.std(ddof=1) / np.sqrt(cost.size)
    assert abs(cost.mean() - exact) <= 4 * se, (cost.mean(), exact, se)


# ---------------------------------------------------------------------------------------------
# Regularisation and a non-convex model
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("reg", [0.1, 2.0])
def test_regularised_value_is_exact_cost_of_its_gains(reg):
    lqg = random_lqg(41, 12, 3, 2, 2, 3, mult_noise=0.5)
    gains, value = backward_pass(lqg, reg)
    assert rel_err(value.expected_cost, policy_cost(lqg, gains)) <= RTOL
    _, opt = backward_pass(lqg)
    assert float(value.expected_cost) > float(opt.expected_cost)    # shifted gains are worse
    structured_vs_augmented(lqg, reg, label=f"regularised {lqg!r}")


def test_value_is_exact_cost_to_go_of_any_gains():
    """The value update holds for whatever gains the step's gains_fn returns (derivation §4)."""
    lqg = random_lqg(42, 12, 3, 2, 2, 3, mult_noise=0.5)

    def detuned(H, reg, g, G, bounds=None, warm=None):
        ok, I, K = unconstrained_gains(H, reg, g, G)
        return ok, 0.6 * I + 0.05, 0.5 * K

    gains, out, ok = jax.jit(lambda q: structured_scan(q, 0.0, store_value=True, gains_fn=detuned))(lqg)
    assert bool(ok)
    assert rel_err(out[0][0], policy_cost(lqg, gains)) <= RTOL


def _detuned(H, reg, g, G, bounds=None, warm=None):
    ok, I, K = unconstrained_gains(H, reg, g, G)
    return ok, 0.6 * I + 0.05, 0.5 * K


@pytest.mark.parametrize("shape", [SHAPES[i] for i in (2, 4, 5, 8)], ids=lambda s: "K{}-n{}-d{}-p{}-l{}".format(*s))
@pytest.mark.parametrize("gains_fn, reg", [(unconstrained_gains, 0.0), (unconstrained_gains, 0.5),
                                           (_detuned, 0.0)], ids=["optimal", "regularised", "detuned"])
def test_predicted_change_is_the_exact_cost_of_the_scaled_feedforward(shape, gains_fn, reg):
    """The line search's model (ilqg.line_search.predicted_change: J(0; alpha) - J(0; 0) = alpha a + alpha^2 b,
    from a linear rollout) against the exact expected cost (second moments) of the policy with
    feedforward alpha I and the same feedback, at alpha = 1/2 and 1 (two equations fix a and b)."""
    lqg = random_lqg(43, *shape, mult_noise=0.5)
    gains, out, _ = jax.jit(lambda q: structured_scan(q, reg, store_value=False, gains_fn=gains_fn))(lqg)
    S = jnp.concatenate([out[2], lqg.D[-1:]])
    got_a, got_b = predicted_change(lqg, to_slots(gains), S)
    cost = lambda alpha: float(policy_cost(lqg, gains._replace(feedforward=alpha * gains.feedforward)))
    full, half = cost(1.0) - cost(0.0), cost(0.5) - cost(0.0)
    b = 2 * full - 4 * half
    a = full - b
    scale = abs(cost(0.0))
    assert abs(float(got_a) - a) <= RTOL * scale, (float(got_a), a)
    assert abs(float(got_b) - b) <= RTOL * scale, (float(got_b), b)
    if gains_fn is not _detuned:
        assert a < 0                                        # the LQG's own step is a descent direction


@pytest.mark.parametrize("shape, block", [(SHAPES[0], 1), (SHAPES[2], 1), (SHAPES[4], 1), (SHAPES[5], 1),
                                          (SHAPES[8], 1), (SHAPES[8], 3)],
                         ids=lambda s: "K{}-n{}-d{}-p{}-l{}".format(*s) if isinstance(s, tuple) else f"block{s}")
@pytest.mark.parametrize("gains_fn, reg", [(unconstrained_gains, 0.5), (_detuned, 0.0)],
                         ids=["regularised", "detuned"])
def test_backward_pass_predicts_what_the_forward_pass_predicts(shape, block, gains_fn, reg):
    """(a, b) accumulated by the structured pass (``predict=True``, derivation §12) == the forward
    pass ``predicted_change``, which the test above checks against exact expected costs."""
    lqg = random_lqg(44, *shape, mult_noise=0.5)
    gains, out, _, (a, b) = jax.jit(lambda q: structured_slot_scan(
        q, reg, store_value=False, gains_fn=gains_fn, block=block, predict=True))(lqg)
    want_a, want_b = predicted_change(lqg, gains, jnp.concatenate([out[2], lqg.D[-1:]]))
    scale = abs(float(out[0][0])) + abs(float(want_a)) + abs(float(want_b))
    assert abs(float(a) - float(want_a)) <= RTOL * scale, (float(a), float(want_a))
    assert abs(float(b) - float(want_b)) <= RTOL * scale, (float(b), float(want_b))


@pytest.mark.parametrize("block", [1, 3])
def test_leaving_S_out_changes_nothing_else(block):
    """``store_S=False`` (the solver without noise) drops s and S from the outputs; the gains,
    s_tilde, the flag and the line search's model must be the same numbers."""
    lqg = random_lqg(45, *SHAPES[8])
    full = structured_slot_scan(lqg, 0.1, store_value=False, block=block, predict=True)
    lean = structured_slot_scan(lqg, 0.1, store_value=False, block=block, predict=True, store_S=False)
    assert len(full[1]) == 3 and len(lean[1]) == 1
    for got, want in [(lean[0], full[0]), (lean[1][0], full[1][0]), (lean[2], full[2]), (lean[3], full[3])]:
        for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    with pytest.raises(ValueError, match="store_S=False needs store_value=False"):
        structured_slot_scan(lqg, store_value=True, store_S=False)


def test_negative_definite_E_is_flagged_not_raised():
    a = random_arrays(51, 5, 4, 4, 3, 2)
    a["E"] = np.broadcast_to(-10.0 * np.eye(4), a["E"].shape).copy()
    a["N"] = np.zeros_like(a["N"])
    lqg = DelayedLQG(**a)
    gains, value = backward_pass(lqg)
    assert not bool(value.positive_definite)
    assert not bool(augmented_backward_pass(lqg)[1].positive_definite)
    assert np.isnan(np.asarray(gains.feedforward)).any()
    # A large enough shift makes every H + reg I definite again.
    assert bool(backward_pass(lqg, 1e3)[1].positive_definite)


# ---------------------------------------------------------------------------------------------
# The printed formulas are wrong: a literal numpy recursion with the errata undone one at a time
# ---------------------------------------------------------------------------------------------

def numpy_theorem1(a, variant="corrected"):
    """Eq. (8) in the unified zero-padded form (N = 0 as in the paper). ``variant``:

    "corrected"  the errata page's recursion;
    "E1"         the printed case boundary: Case 1 (no R^{(l-1)(l-1)}, Rt^{l-1}, r^{l-1}) for k >= K-l;
    "E3E4"       the printed R^{i0}_{k-1} = (Rt^{i-1})'B1 - (M^0)'H M^{i-1};
    "E5"         the printed R^{ij}_{k-1} = R^{(i-1)(j-1)} - (M^{i-1})'H M^{j-1}.
    Returns J(0) and the gains I, L, M (time-major, as the library).
    """
    A, B0, B1, c, C0, C1 = (a[k] for k in ("A", "B0", "B1", "c", "C0", "C1"))
    l = a["delay_steps"]
    K, n, d = B0.shape
    st_, s, S = a["d_tilde"][K], a["d"][K], a["D"][K]
    r, Rt, R = np.zeros((l, d)), np.zeros((l, n, d)), np.zeros((l, l, d, d))
    Is, Ls, Ms = np.zeros((K, d)), np.zeros((K, d, n)), np.zeros((K, l, d, d))
    for k in range(K, 0, -1):                           # J(k) -> J(k-1), data at k-1
        j = k - 1
        Ak, B0k, B1k, ck, C0k, C1k = A[j], B0[j], B1[j], c[j], C0[j], C1[j]
        case1 = variant == "E1" and k >= K - l
        RL, RtL, rL = (0 * R[-1, -1], 0 * Rt[-1], 0 * r[-1]) if case1 else (R[-1, -1], Rt[-1], r[-1])
        sumC = lambda X, Y: sum(X[q].T @ S @ Y[q] for q in range(len(X))) if len(X) else 0.0
        H = a["E"][j] + B0k.T @ S @ B0k + sumC(C0k, C0k) + RL + B0k.T @ RtL + RtL.T @ B0k
        Hi = np.linalg.inv(H)
        I = -Hi @ (a["e"][j] + B0k.T @ s + sum(C0k[q].T @ S @ ck[q] for q in range(len(ck))) + rL)
        L = -Hi @ (S @ B0k + RtL).T @ Ak
        M = np.zeros((l, d, d))
        M[0] = -Hi @ (B0k.T @ S @ B1k + sumC(C0k, C1k) + RtL.T @ B1k)
        for i in range(1, l):
            M[i] = -Hi @ (B0k.T @ Rt[i - 1] + (0 * R[-1, i - 1] if case1 else R[-1, i - 1]))
        st_ = a["d_tilde"][j] + st_ + sum(ck[q] @ S @ ck[q] for q in range(len(ck))) - I @ H @ I
        s_new = a["d"][j] + Ak.T @ s - L.T @ H @ I
        S_new = a["D"][j] + Ak.T @ S @ Ak - L.T @ H @ L
        r_new, Rt_new, R_new = np.zeros_like(r), np.zeros_like(Rt), np.zeros_like(R)
        if l:
            r_new[0] = B1k.T @ s + sum(C1k[q].T @ S @ ck[q] for q in range(len(ck))) - M[0].T @ H @ I
            Rt_new[0] = Ak.T @ S @ B1k - L.T @ H @ M[0]
            R_new[0, 0] = B1k.T @ S @ B1k + sumC(C1k, C1k) - M[0].T @ H @ M[0]
        for i in range(1, l):
            r_new[i] = r[i - 1] - M[i].T @ H @ I
            Rt_new[i] = Ak.T @ Rt[i - 1] - L.T @ H @ M[i]
            R_new[i, 0] = Rt[i - 1].T @ B1k - (M[0].T @ H @ M[i - 1] if variant == "E3E4" else M[i].T @ H @ M[0])
            R_new[0, i] = R_new[i, 0].T
            for jj in range(1, l):
                mi, mj = (M[i - 1], M[jj - 1]) if variant == "E5" else (M[i], M[jj])
                R_new[i, jj] = R[i - 1, jj - 1] - mi.T @ H @ mj
        s, S, r, Rt, R = s_new, S_new, r_new, Rt_new, R_new
        Is[j], Ls[j], Ms[j] = I, L, M
    return st_, Is, Ls, Ms


@pytest.mark.parametrize("variant", ["corrected", "E1", "E3E4", "E5"])
def test_printed_formulas_disagree_with_augmentation(variant):
    a = random_arrays(61, 12, 3, 2, 2, 3, cross=False)
    lqg = DelayedLQG(**a)
    ga, va = augmented_backward_pass(lqg)
    j0, I, L, M = numpy_theorem1(a, variant)
    err = max(rel_err(j0, va.expected_cost), rel_err(I, ga.feedforward),
              rel_err(L, ga.state_feedback), rel_err(M, ga.delay_feedback))
    if variant == "corrected":
        assert err <= RTOL
        structured_vs_augmented(lqg, label="errata problem")          # and so does the library
    else:
        assert err > 1e-3, err
        assert rel_err(j0, va.expected_cost) > 1e-4                   # the optimum itself moves
        j_printed = float(policy_cost(lqg, Gains(I, L, M)))           # and its policy is worse
        assert j_printed > float(va.expected_cost) * (1 + 1e-9), (j_printed, float(va.expected_cost))


# ---------------------------------------------------------------------------------------------
# Input validation: every rule, with its message
# ---------------------------------------------------------------------------------------------

K0, N0, D0, P0 = 4, 3, 2, 1                     # K, n, d, p of the validation problem (l = 2)


def _base(**changes):
    a = random_arrays(71, K0, N0, D0, P0, 2)
    a.update(changes)
    return a


@pytest.mark.parametrize("name, shape, message", [
    ("A", (4, 3), "A must have shape (*, *, *); got shape (4, 3)"),
    ("A", (4, 3, 4), "A must have shape (4, 3, 3); got shape (4, 3, 4)"),
    ("A", (0, 3, 3), "A must hold at least one time step (K >= 1); got shape (0, 3, 3)"),
    ("B0", (5, 3, 2), "B0 must have shape (4, 3, *); got shape (5, 3, 2)"),
    ("B1", (4, 3, 3), "B1 must have shape (4, 3, 2); got shape (4, 3, 3)"),
    ("c", (4, 1, 4), "c must have shape (4, *, 3); got shape (4, 1, 4)"),
    ("C0", (4, 2, 3, 2), "C0 must have shape (4, 1, 3, 2); got shape (4, 2, 3, 2)"),
    ("C1", (4, 1, 3, 2, 1), "C1 must have shape (4, 1, 3, 2); got shape (4, 1, 3, 2, 1)"),
    ("d_tilde", (4,), "d_tilde must have shape (5,); got shape (4,)"),
    ("d", (4, 3), "d must have shape (5, 3); got shape (4, 3)"),
    ("D", (4, 3, 3), "D must have shape (5, 3, 3); got shape (4, 3, 3)"),
    ("e", (5, 2), "e must have shape (4, 2); got shape (5, 2)"),
    ("E", (4, 2, 3), "E must have shape (4, 2, 2); got shape (4, 2, 3)"),
    ("N", (4, 3, 2), "N must have shape (4, 2, 3); got shape (4, 3, 2)"),
])
def test_wrong_shape_names_argument_and_shape(name, shape, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        DelayedLQG(**_base(**{name: np.zeros(shape)}))


@pytest.mark.parametrize("name, value", [("A", np.nan), ("B1", np.inf), ("c", -np.inf), ("D", np.nan),
                                          ("E", np.inf), ("d_tilde", np.nan), ("N", np.nan)])
def test_non_finite_values_are_refused(name, value):
    a = _base()
    arr = np.array(a[name], dtype=float)
    arr.flat[arr.size - 1] = value
    index = tuple(int(i) for i in np.unravel_index(arr.size - 1, arr.shape))
    with pytest.raises(ValueError, match=re.escape(f"{name} must be finite; got a non-finite value at index {index}")):
        DelayedLQG(**_base(**{name: arr}))


@pytest.mark.parametrize("bad, shown", [(-1, "-1"), (2.5, "2.5"), (True, "True"), (False, "False"),
                                        ("3", "'3'"), (None, "None")])
def test_bad_delay_steps(bad, shown):
    with pytest.raises(ValueError, match=re.escape(
            f"delay_steps must be a non-negative integer number of steps; got {shown}")):
        DelayedLQG(**_base(delay_steps=bad))


@pytest.mark.parametrize("good", [0, 2.0, np.int64(3)])
def test_integral_delay_steps_are_accepted(good):
    lqg = DelayedLQG(**_base(delay_steps=good))
    assert lqg.delay_steps == int(good) and type(lqg.delay_steps) is int


@pytest.mark.parametrize("name", ["D", "E"])
def test_asymmetric_cost_matrices_are_refused(name):
    bad = np.array(_base()[name])
    bad[1, 0, 1] += 0.5
    with pytest.raises(ValueError, match=f"{name} must be symmetric in its last two axes; got an asymmetry of 0.5"):
        DelayedLQG(**_base(**{name: bad}))


def test_non_numeric_array_is_a_type_error():
    with pytest.raises(TypeError, match="A must be an array of numbers"):
        DelayedLQG(**_base(A=[["x"]]))


def test_noise_none_must_be_all_or_nothing():
    lqg = DelayedLQG(**_base(c=None, C0=None, C1=None))
    assert lqg.n_noise == 0
    with pytest.raises(ValueError, match=re.escape("c must have shape (4, *, 3); got shape ()")):
        DelayedLQG(**_base(c=None))


@pytest.fixture(scope="module")
def small_problem():
    lqg = DelayedLQG(**_base())
    return lqg, Gains(np.zeros((K0, D0)), np.zeros((K0, D0, N0)), np.zeros((K0, 2, D0, D0)))


@pytest.mark.parametrize("field, shape, message", [
    ("feedforward", (5, 2), "gains.feedforward must have shape (4, 2); got shape (5, 2)"),
    ("state_feedback", (4, 3, 2), "gains.state_feedback must have shape (4, 2, 3); got shape (4, 3, 2)"),
    ("delay_feedback", (4, 3, 2, 2), "gains.delay_feedback must have shape (4, 2, 2, 2); got shape (4, 3, 2, 2)"),
])
@pytest.mark.parametrize("consumer", ["policy_cost", "simulate_lqg"])
def test_wrong_gain_shapes(small_problem, field, shape, message, consumer):
    lqg, gains = small_problem
    bad = gains._replace(**{field: np.zeros(shape)})
    call = (lambda: policy_cost(lqg, bad)) if consumer == "policy_cost" else (lambda: simulate_lqg(lqg, bad, 3))
    with pytest.raises(ValueError, match=re.escape(message)):
        call()


def test_non_finite_gains_are_refused(small_problem):
    lqg, gains = small_problem
    bad = gains._replace(state_feedback=np.full(gains.state_feedback.shape, np.nan))
    with pytest.raises(ValueError, match=re.escape("gains.state_feedback must be finite; got a non-finite value at index (0, 0, 0)")):
        policy_cost(lqg, bad)


@pytest.mark.parametrize("n_trials, shown", [(0, "0"), (-5, "-5"), (2.5, "2.5"), (True, "True")])
def test_bad_n_trials(small_problem, n_trials, shown):
    lqg, gains = small_problem
    with pytest.raises(ValueError, match=re.escape(f"n_trials must be a positive integer; got {shown}")):
        simulate_lqg(lqg, gains, n_trials)


@pytest.mark.parametrize("K, l", [(5, 0), (5, 1), (4, 3), (3, 7)])
def test_slot_gains_round_trip(K, l):
    """to_slots and from_slots are inverse, and the slot form is the recursion's own: at step k,
    M_k^i multiplies du_{k+i-l}, stored in slot (k+i) mod l."""
    rng = np.random.default_rng(K * 10 + l)
    n, d = 3, 2
    gains = Gains(jnp.asarray(rng.normal(size=(K, d))), jnp.asarray(rng.normal(size=(K, d, n))),
                  jnp.asarray(rng.normal(size=(K, l, d, d))))
    slots = to_slots(gains)
    assert slots.feedback.shape == (K, d, n + l * d)
    for k in range(K):
        for i in range(l):
            s = (k + i) % l
            np.testing.assert_array_equal(slots.feedback[k, :, n + s * d:n + (s + 1) * d], gains.delay_feedback[k, i])
    for got, want in zip(from_slots(slots, n), gains):
        np.testing.assert_array_equal(got, want)


def test_blocked_pass_under_vmap_matches_separate_passes():
    """The blocked pass is a scan over blocks of a scan over steps (no lax.cond), so it batches."""
    lqgs = [random_lqg(seed, 10, 3, 2, 1, 4) for seed in (31, 32)]
    scan = lambda q: structured_scan(q, 0.0, store_value=False, block=3)
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *lqgs)
    batched = jax.jit(jax.vmap(scan))(stacked)
    for i, lqg in enumerate(lqgs):
        separate = jax.jit(scan)(lqg)
        for got, want in zip(jax.tree_util.tree_leaves(batched), jax.tree_util.tree_leaves(separate)):
            np.testing.assert_allclose(np.asarray(got)[i], np.asarray(want), rtol=1e-12, atol=1e-14)
