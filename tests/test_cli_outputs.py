"""The command line's outputs and exit codes (issue 22, items 1-4 and 10): atomic folders with a
manifest, --out checked before computing, one-line errors with their own exit code."""
import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from delayed_ilqr import cli
from delayed_ilqr.experiments import engine, report


def invoke(*args):
    return CliRunner().invoke(cli.main, [str(a) for a in args])


def test_a_second_run_replaces_the_folder_whole_and_lists_its_files(tmp_path):
    out = tmp_path / "d"
    first = invoke("simulate", "arm2", "--delay", "0.05", "--trials", 4, "--out", out)
    assert first.exit_code == 0, first.output
    assert (out / "hand_paths.png").exists()
    refused = invoke("simulate", "point_mass", "--delay", "0.03", "--trials", 4, "--out", out)
    assert refused.exit_code == 2 and "is not empty; pass --overwrite" in refused.output
    second = invoke("simulate", "point_mass", "--delay", "0.03", "--trials", 4, "--out", out, "--overwrite")
    assert second.exit_code == 0, second.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert not (out / "hand_paths.png").exists()                 # the arm's figure did not survive
    assert sorted(manifest["files"]) == sorted(f for f in os.listdir(out) if f != "manifest.json")
    assert manifest["settings"]["model"] == "point_mass" and manifest["version"]
    assert all(os.path.getsize(out / f) == size for f, size in manifest["files"].items())
    assert [p.name for p in tmp_path.iterdir()] == ["d"]         # no staging folder left


def test_an_error_while_computing_leaves_the_old_folder_and_no_staging(tmp_path, monkeypatch):
    out = tmp_path / "d"
    out.mkdir()
    (out / "old.txt").write_text("old")

    def broken(*args, **kwargs):
        raise RuntimeError("disk on fire\nsecond line")

    monkeypatch.setattr(report, "write_runs", broken)
    result = invoke("simulate", "point_mass", "--delay", "0.03", "--trials", 4, "--out", out, "--overwrite")
    assert result.exit_code == cli.ERROR_EXIT == 3
    assert result.output.strip().splitlines()[-1] == \
        "error: RuntimeError: disk on fire (--debug shows the traceback)"
    assert [p.name for p in out.iterdir()] == ["old.txt"] and [p.name for p in tmp_path.iterdir()] == ["d"]
    with pytest.raises(RuntimeError):
        CliRunner().invoke(cli.main, ["--debug", "simulate", "point_mass", "--delay", "0.03", "--trials", "4",
                                      "--out", str(out), "--overwrite"], catch_exceptions=False)


def test_an_out_that_cannot_be_created_is_a_usage_error_before_computing(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setattr(engine, "timed_solve", lambda *a, **k: pytest.fail("computed before checking --out"))
    for out in (blocker, blocker / "sub"):
        result = invoke("solve", "point_mass", "--out", out)
        assert result.exit_code == 2 and "--out" in result.output, result.output
        assert "Traceback" not in result.output


@pytest.mark.parametrize("args, match", [
    (("solve", "point_mass", "--delay", "1e308"), "--delay"),
    (("solve", "point_mass", "--delay", "100"), "below the horizon"),
    (("simulate", "point_mass", "--seed", "99999999999999999999"), "--seed"),
    (("simulate", "point_mass", "--trials", "50000000000"), "GB"),
])
def test_bad_numbers_are_usage_errors(args, match):
    result = invoke(*args)
    assert result.exit_code == 2, result.output
    assert match in result.output and "Traceback" not in result.output


def test_simulate_refuses_more_trials_than_memory_holds():
    import delayed_ilqr as di
    from delayed_ilqr.models import point_mass
    from delayed_ilqr.simulate import memory_estimate
    problem = point_mass(noise=True)
    policy = di.solve(problem).policy
    with pytest.raises(ValueError, match=r"n_trials=50000000000 trials would hold about .* GB"):
        di.simulate(problem, policy, 50_000_000_000)
    p = problem.n_noise
    # an upper bound of the peak: PEAK_FACTOR = 4 times the arrays (tests/test_simulate.py measures it)
    assert memory_estimate(problem, 10, 3) == 4 * 8 * 10 * (61 * 4 + 60 * 2 + 1 + 60 * 3 * p)
