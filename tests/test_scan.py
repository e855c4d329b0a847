"""``_scan.packed_scan`` is ``lax.scan`` with packed inputs and outputs: same results, bit for bit."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from delayed_ilqr._scan import packed_scan


def _step(carry, data):
    x, count = carry
    k, A, b, empty, flag = data
    x = A @ x + b + jnp.sum(empty)
    count = count + k + flag.astype(k.dtype)
    return (x, count), {"x": x, "k2": 2 * k, "pair": (A.T, jnp.zeros((0, 3))), "flag": ~flag}


@pytest.mark.parametrize("reverse", [False, True])
def test_packed_scan_matches_lax_scan(reverse):
    rng = np.random.default_rng(0)
    K = 7
    data = (jnp.arange(K), jnp.asarray(rng.normal(size=(K, 3, 3))), jnp.asarray(rng.normal(size=(K, 3))),
            jnp.zeros((K, 0, 2)), jnp.asarray(rng.random(K) > 0.5))
    init = (jnp.ones(3), jnp.asarray(0))
    want = jax.lax.scan(_step, init, data, reverse=reverse)
    got = jax.jit(lambda i, d: packed_scan(_step, i, d, reverse=reverse))(init, data)
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(want)
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        assert g.shape == w.shape and g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)
