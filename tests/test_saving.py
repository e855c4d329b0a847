"""Saved solutions and policies (delayed_ilqr.saving): bitwise round trips, simulate on a loaded
policy, the header and the refusals (the command line's files: tests/test_cli.py)."""
import json
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr import saving
from delayed_ilqr.models import point_mass


@pytest.fixture(scope="module")
def solved():
    problem = point_mass(delay=0.03, noise=True)
    return problem, di.solve(problem)


def assert_same_record(a, b):
    """Same type, same fields, arrays bitwise equal (NaN in the trace's tail included)."""
    assert type(a) is type(b)
    if isinstance(a, di.Estimator):
        assert a.sensory_delay == b.sensory_delay and isinstance(b.sensory_delay, int)
        names = a._arrays
    else:
        assert a._fields == b._fields
        names = a._fields
    for name in names:
        x, y = getattr(a, name), getattr(b, name)
        if x is None:
            assert y is None, name
        elif isinstance(x, (tuple, di.Estimator)):
            assert_same_record(x, y)
        else:
            x, y = np.asarray(x), np.asarray(y)
            assert x.dtype == y.dtype and x.shape == y.shape, name
            assert x.tobytes() == y.tobytes(), name


def test_solution_round_trip_is_bitwise(solved, tmp_path):
    problem, sol = solved
    sol.save(tmp_path / "sol.npz", problem, info=dict(note="P1-noisy"))
    back = di.load(tmp_path / "sol.npz")
    assert_same_record(sol, back)
    assert back.status is di.Status(int(sol.status)) and back.converged
    meta = di.load_metadata(tmp_path / "sol.npz")
    assert meta["format_version"] == saving.FORMAT_VERSION and meta["kind"] == "Solution"
    assert (meta["dt"], meta["delay_steps"], meta["horizon"], meta["n_states"], meta["n_controls"]) == (0.01, 3, 60, 4, 2)
    assert meta["delay"] == pytest.approx(0.03) and meta["problem"]["name"] == "point_mass"
    assert meta["arrays"]["policy.delay_feedback"] == dict(shape=[60, 3, 2, 2], dtype="<f8")
    assert meta["info"] == dict(note="P1-noisy")


def test_policy_round_trip_and_simulate_on_the_loaded_policy(solved, tmp_path):
    problem, sol = solved
    sol.policy.save(tmp_path / "policy")                       # NumPy appends .npz
    policy = di.load(tmp_path / "policy.npz")
    assert_same_record(sol.policy, policy)
    assert "dt" not in di.load_metadata(tmp_path / "policy.npz")     # no problem given: no time step
    a = di.simulate(problem, sol.policy, 32, seed=5)
    b = di.simulate(problem, policy, 32, seed=5)
    for x, y in zip(a, b):
        assert np.asarray(x).tobytes() == np.asarray(y).tobytes()


def test_a_policy_with_its_delayed_filter_round_trips_and_simulates_the_same(tmp_path):
    problem = point_mass(delay=0.03, noise=True, sensory_delay=0.02)
    sol = di.solve(problem)
    assert isinstance(sol.policy.estimator, di.Estimator) and sol.policy.estimator.sensory_delay == 2
    sol.save(tmp_path / "observed.npz", problem)
    back = di.load(tmp_path / "observed.npz")
    assert_same_record(sol, back)
    assert di.load_metadata(tmp_path / "observed.npz")["types"]["policy.estimator"] == "Estimator"
    a = di.simulate(problem, sol.policy, 16, seed=2)
    b = di.simulate(problem, back.policy, 16, seed=2)
    for x, y in zip(a, b):
        assert np.asarray(x).tobytes() == np.asarray(y).tobytes()


def test_batched_solution_round_trip(solved, tmp_path):
    """A batch as ``jax.vmap(solve)`` returns it: every field with a leading axis, status an array."""
    problem, sol = solved
    sols = jax.tree_util.tree_map(lambda *a: jnp.stack(a), sol, sol._replace(cost=sol.cost + 1))
    di.saving.save(tmp_path / "batch.npz", sols)
    back = di.load(tmp_path / "batch.npz")
    assert_same_record(sols, back)
    assert di.load_metadata(tmp_path / "batch.npz")["horizon"] == problem.horizon


def _rewrite_header(src, dst, **changes):
    with np.load(src) as npz:
        arrays = {k: npz[k] for k in npz.files}
    header = json.loads(arrays["__metadata__"].tobytes())
    header.update(changes)
    arrays["__metadata__"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    np.savez(dst, **arrays)


def test_unknown_version_and_foreign_files_are_refused(solved, tmp_path):
    problem, sol = solved
    sol.save(tmp_path / "sol.npz")
    _rewrite_header(tmp_path / "sol.npz", tmp_path / "v2.npz", format_version=2)
    with pytest.raises(ValueError, match="has format_version 2; this delayed-ilqr .* reads format_version 1 only"):
        di.load(tmp_path / "v2.npz")
    _rewrite_header(tmp_path / "sol.npz", tmp_path / "unknown.npz", types={"": "Solution", "policy": "Smoother",
                                                                             "trace": "Trace"})
    with pytest.raises(ValueError, match=r"records of unknown type \['Smoother'\]"):
        di.load(tmp_path / "unknown.npz")
    np.savez(tmp_path / "plain.npz", x=np.zeros(3))
    with pytest.raises(ValueError, match="is not a delayed-ilqr file"):
        di.load(tmp_path / "plain.npz")
    with zipfile.ZipFile(tmp_path / "sol.npz") as z, zipfile.ZipFile(tmp_path / "extra.npz", "w") as out:
        for item in z.namelist():
            out.writestr(item, z.read(item))
        with out.open("policy.extra.npy", "w") as f:
            np.save(f, np.zeros(2))
    with pytest.raises(ValueError, match=r"entries \['policy.extra'\] are not fields of Solution"):
        di.load(tmp_path / "extra.npz")
    with pytest.raises(TypeError, match="obj must be a delayed_ilqr.Solution or Policy; got dict"):
        saving.save(tmp_path / "x.npz", {})
    with pytest.raises(ValueError, match="info must be JSON-serialisable"):
        sol.save(tmp_path / "x.npz", info=dict(a=np.zeros(2)))
    with pytest.raises(ValueError, match="problem must match the saved gains"):
        sol.save(tmp_path / "x.npz", point_mass(horizon=30))


def test_a_missing_optional_field_takes_its_default(solved, tmp_path, monkeypatch):
    """The rule that lets a record gain an optional field (a later Policy's estimator) and still
    read the files written before it."""
    from typing import NamedTuple, Optional

    class Policy2(NamedTuple):
        x_nominal: jax.Array
        u_nominal: jax.Array
        feedforward: jax.Array
        state_feedback: jax.Array
        delay_feedback: jax.Array
        estimator: Optional[jax.Array] = None

    problem, sol = solved
    sol.policy.save(tmp_path / "old.npz")
    monkeypatch.setitem(saving._RECORDS, "Policy", Policy2)
    back = di.load(tmp_path / "old.npz")
    assert type(back) is Policy2 and back.estimator is None
    assert np.asarray(back.state_feedback).tobytes() == np.asarray(sol.policy.state_feedback).tobytes()
