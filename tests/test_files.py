"""The files the library writes and reads (delayed_ilqr._files): every writer goes through the one
atomic-write helper, which leaves the old file whole when interrupted; damaged inputs are one
error naming the file."""
import ast
import pathlib

import numpy as np
import pytest

from delayed_ilqr import _files

SRC = pathlib.Path(__file__).resolve().parents[1] / "src" / "delayed_ilqr"
# calls that write a file in place (not atomically): methods of any object, and functions of modules
METHODS = {"write_text", "write_bytes", "savefig", "tofile", "to_netcdf"}
FUNCTIONS = {("np", "save"), ("np", "savez"), ("np", "savez_compressed"), ("json", "dump"), ("pickle", "dump")}


def _direct_writes(tree) -> list[str]:
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
        owner = ast.unparse(f.value) if isinstance(f, ast.Attribute) else ""
        if (isinstance(f, ast.Attribute) and name in METHODS and owner != "_files") or (owner, name) in FUNCTIONS:
            found.append(f"{ast.unparse(node)[:80]} (line {node.lineno})")
        if name == "open" and len(node.args) > 1 and isinstance(node.args[1], ast.Constant) \
                and any(c in str(node.args[1].value) for c in "wax"):
            found.append(f"{ast.unparse(node)[:80]} (line {node.lineno})")
    return found


def test_every_file_the_library_writes_goes_through_the_atomic_helper():
    """A source check: no module but _files.py writes a file directly (Zarr chunks excepted: the
    sweep store verifies them by checksum)."""
    offenders = {}
    for path in sorted(SRC.rglob("*.py")):
        if path.name == "_files.py":
            continue
        found = _direct_writes(ast.parse(path.read_text()))
        if found:
            offenders[str(path.relative_to(SRC))] = found
    assert offenders == {}


def test_an_interrupted_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "a.json"
    _files.write_json(target, {"old": 1})
    with pytest.raises(KeyboardInterrupt):
        with _files.atomic_file(target) as f:
            f.write(b'{"new"')
            raise KeyboardInterrupt
    assert _files.read_json(target, "a test file") == {"old": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]
    _files.savez(tmp_path / "b", dict(x=np.arange(3)))            # exactly that name
    with _files.open_npz(tmp_path / "b", "a test archive") as npz:
        assert npz["x"].tolist() == [0, 1, 2]
    with pytest.raises(_files.FileFormatError, match=r"a.json: is not an NPZ archive .*expected a test archive"):
        _files.open_npz(target, "a test archive")


def test_the_fit_data_file_is_read_through_the_same_checks(tmp_path):
    from delayed_ilqr.experiments import fitting
    (tmp_path / "data.npz").write_bytes(b"x,y\n1,2\n")
    with pytest.raises(_files.FileFormatError, match=r"data.npz: is not an NPZ archive .*save_reach_data"):
        fitting.load_reach_data(tmp_path / "data.npz")
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(_files.FileFormatError, match=r"one.npy: is a single NumPy array"):
        fitting.load_reach_data(tmp_path / "one.npy")


def test_an_atomic_write_gives_the_permissions_of_an_ordinary_new_file(tmp_path):
    _files.write_text(tmp_path / "atomic.txt", "a")
    (tmp_path / "plain.txt").write_text("a")
    assert (tmp_path / "atomic.txt").stat().st_mode == (tmp_path / "plain.txt").stat().st_mode
