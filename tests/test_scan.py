"""``_kernels.scan.packed_scan`` is ``lax.scan`` with packed inputs and outputs: same results, bit for bit."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from delayed_ilqr._kernels.scan import _PACK_MAX, Blocks, packed_scan

K = 12
BIG = _PACK_MAX + 72          # per-step leaves above _PACK_MAX are passed unpacked


def _step(carry, data):
    x, count = carry
    k, A, b, empty, flag, big = data
    x = A @ x + b + jnp.sum(empty) + big[:3]
    count = count + k + flag.astype(k.dtype)
    return (x, count), {"x": x, "k2": 2 * k, "pair": (A.T, jnp.zeros((0, 3))), "flag": ~flag, "big": 2 * big}


def _data():
    rng = np.random.default_rng(0)
    return (jnp.arange(K), jnp.asarray(rng.normal(size=(K, 3, 3))), jnp.asarray(rng.normal(size=(K, 3))),
            jnp.zeros((K, 0, 2)), jnp.asarray(rng.random(K) > 0.5), jnp.asarray(rng.normal(size=(K, BIG))))


def _assert_same(got, want):
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(want)
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        assert g.shape == w.shape and g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("reverse", [False, True])
def test_packed_scan_matches_lax_scan(reverse):
    init = (jnp.ones(3), jnp.asarray(0))
    want = jax.lax.scan(_step, init, _data(), reverse=reverse)
    got = jax.jit(lambda i, d: packed_scan(_step, i, d, reverse=reverse))(init, _data())
    _assert_same(got, want)


@pytest.mark.parametrize("reverse", [False, True])
def test_blocks_apply_flush_after_every_block(reverse):
    """block = 4: flush after steps 4, 8, 12 (in scan order), as a plain loop does it."""
    flush = lambda carry: (0.5 * carry[0], carry[1] + 100)
    init = (jnp.ones(3), jnp.asarray(0))
    data = _data()
    carry, outs = init, []
    for j in (range(K - 1, -1, -1) if reverse else range(K)):
        carry, y = _step(carry, jax.tree_util.tree_map(lambda x: x[j], data))
        outs.append(y)
        if len(outs) % 4 == 0:
            carry = flush(carry)
    outs = outs[::-1] if reverse else outs
    want = carry, jax.tree_util.tree_map(lambda *ys: jnp.stack(ys), *outs)
    got = jax.jit(lambda i, d: packed_scan(_step, i, d, reverse=reverse, blocks=Blocks(4, flush)))(init, data)
    _assert_same(got, want)


def test_block_must_divide_the_length():
    with pytest.raises(ValueError, match=r"the scan length \(12\) must be a multiple of the block size \(5\)"):
        packed_scan(_step, (jnp.ones(3), jnp.asarray(0)), _data(), blocks=Blocks(5, lambda c: c))
