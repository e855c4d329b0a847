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


# -- atomic saving and damaged or foreign files -----------------------------------------------------

def test_a_save_interrupted_mid_write_leaves_the_old_file_whole(solved, tmp_path, monkeypatch):
    """A process interrupted while writing over an existing file (here: an exception from inside
    the array writer, after part of the archive is on disk) keeps the old file loadable and
    leaves no temporary file."""
    problem, sol = solved
    path = tmp_path / "sol.npz"
    sol.save(path, problem)
    before = path.read_bytes()
    real, written = np.lib.format.write_array, []

    def dies_after_two_arrays(fp, array, *args, **kwargs):
        if len(written) == 2:
            raise KeyboardInterrupt
        written.append(1)
        return real(fp, array, *args, **kwargs)

    monkeypatch.setattr(np.lib.format, "write_array", dies_after_two_arrays)
    with pytest.raises(KeyboardInterrupt):
        sol._replace(cost=sol.cost + 1).save(path, problem)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert_same_record(sol, di.load(path))
    assert [p.name for p in tmp_path.iterdir()] == ["sol.npz"]


def _damaged_files(folder, good):
    """{case: path} of files that are not delayed-ilqr files, or damaged ones."""
    data = good.read_bytes()
    files = dict(empty=b"", garbage=b"\x00garbage" * 20, truncated=data[: len(data) // 2],
                 text=b"x,y\n1,2\n", utf16=("\ufeffnot a file").encode("utf-16"),
                 pickle=__import__("pickle").dumps({"x": 1}), zeros=bytes(4096))
    out = {}
    for name, content in files.items():
        out[name] = folder / f"{name}.npz"
        out[name].write_bytes(content)
    np.save(folder / "single.npy", np.zeros(3))
    out["npy"] = folder / "single.npy"
    out["folder"] = folder / "a_folder.npz"
    out["folder"].mkdir()
    out["missing"] = folder / "missing.npz"
    # an archive whose header is not JSON, not UTF-8, not an object, or lacks the keys load needs
    with np.load(good) as npz:
        arrays = {k: npz[k] for k in npz.files}
    for name, header in (("badjson", b"{not json"), ("badutf8", b"\xff\xfe\x00"), ("list", b"[1, 2]"),
                         ("nokeys", b'{"format": "delayed-ilqr", "format_version": 1}'),
                         ("badtypes", json.dumps(dict(json.loads(arrays["__metadata__"].tobytes()),
                                                      types="Solution")).encode())):
        np.savez(folder / f"{name}.npz", **dict(arrays, __metadata__=np.frombuffer(header, np.uint8)))
        out[name] = folder / f"{name}.npz"
    # a damaged entry: the archive's directory is intact, one array's bytes are not
    with zipfile.ZipFile(good) as z, zipfile.ZipFile(folder / "badentry.npz", "w") as w:
        for item in z.namelist():
            w.writestr(item, z.read(item)[:20] if item == "x.npy" else z.read(item))
    out["badentry"] = folder / "badentry.npz"
    # a pickled object array in place of an array
    np.savez(folder / "objects.npz", **dict(arrays, x=np.array([{"a": 1}], dtype=object)))
    out["objects"] = folder / "objects.npz"
    return out


def test_damaged_and_foreign_files_are_refused_with_one_error_naming_the_file(solved, tmp_path):
    problem, sol = solved
    sol.save(tmp_path / "good.npz", problem)
    for case, path in _damaged_files(tmp_path, tmp_path / "good.npz").items():
        for reader in (di.load, di.load_metadata):
            if reader is di.load_metadata and case in ("badentry", "objects", "nokeys", "badtypes"):
                continue                                   # the header alone is fine
            with pytest.raises(saving.FileFormatError) as info:
                reader(path)
            message = str(info.value)
            assert message.startswith(str(path)), (case, message)
            assert "delayed-ilqr file" in message, (case, message)
            assert isinstance(info.value, ValueError)


def _rewrite(src, dst, header_changes=None, arrays_changes=None):
    with np.load(src) as npz:
        arrays = {k: npz[k] for k in npz.files}
    header = json.loads(arrays["__metadata__"].tobytes())
    header.update(header_changes or {})
    arrays.update(arrays_changes or {})
    arrays["__metadata__"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    np.savez(dst, **arrays)


def test_a_header_that_contradicts_the_arrays_is_refused(solved, tmp_path):
    problem, sol = solved
    good = tmp_path / "good.npz"
    sol.save(good, problem)
    header = di.load_metadata(good)
    shapes = dict(header["arrays"], x=dict(shape=[61, 5], dtype="<f8"))
    cases = [
        (dict(horizon=50), None, r"horizon 50 contradicts the arrays \(K=60"),
        (dict(n_states=3), None, r"n_states 3"),
        (dict(n_controls=1), None, r"n_controls 1"),
        (dict(delay_steps=2), None, r"delay_steps 2"),
        (dict(kind="Policy"), None, r"kind 'Policy' .* 'Solution'"),
        (dict(kind="Smoother"), None, r"kind must be"),
        (dict(arrays=shapes), None, r"entry 'x' .* shape \[61, 4\] .* header .* \[61, 5\]"),
        (None, dict(u=np.zeros((60, 3))), r"entry 'u' .* shape"),
        (dict(arrays=dict(header["arrays"], u=dict(shape=[60, 3], dtype="<f8"))), dict(u=np.zeros((60, 3))),
         r"u must be \[K, d\] \(K=60, d=2\); got shape \[60, 3\]"),
    ]
    for i, (changes, arrays, match) in enumerate(cases):
        bad = tmp_path / f"bad{i}.npz"
        _rewrite(good, bad, changes, arrays)
        with pytest.raises(saving.FileFormatError, match=match):
            di.load(bad)


def test_float32_arrays_come_back_float64(solved, tmp_path):
    problem, sol = solved
    single = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32) if np.asarray(a).dtype == np.float64 else a,
                                    sol.policy)
    saving.save(tmp_path / "f32.npz", single)
    back = di.load(tmp_path / "f32.npz")
    for name in ("x_nominal", "u_nominal", "state_feedback", "delay_feedback"):
        a = getattr(back, name)
        assert a.dtype == jnp.float64, name
        assert np.array_equal(np.asarray(a), np.asarray(getattr(single, name), np.float64)), name


def test_save_and_load_agree_on_a_name_without_suffix(solved, tmp_path):
    problem, sol = solved
    sol.save(tmp_path / "x")
    assert [p.name for p in tmp_path.iterdir()] == ["x.npz"]
    assert_same_record(sol, di.load(tmp_path / "x"))
    assert di.load_metadata(tmp_path / "x")["kind"] == "Solution"


def test_a_policy_loaded_for_a_plant_of_another_time_step_is_refused(solved, tmp_path):
    problem, sol = solved
    sol.policy.save(tmp_path / "p.npz", problem)
    assert_same_record(sol.policy, di.load(tmp_path / "p.npz", problem=problem))
    other = point_mass(delay=0.03, noise=True, dt=0.005, horizon=60)
    with pytest.raises(ValueError, match=r"p.npz: saved for dt = 0.01 s, but the problem has dt = 0.005 s"):
        di.load(tmp_path / "p.npz", problem=other)
    with pytest.raises(ValueError, match=r"horizon"):
        di.load(tmp_path / "p.npz", problem=point_mass(delay=0.03, horizon=30))
    sol.policy.save(tmp_path / "nodt.npz")                 # no problem recorded: the sizes only
    with pytest.warns(UserWarning, match="records no time step"):
        di.load(tmp_path / "nodt.npz", problem=other)
