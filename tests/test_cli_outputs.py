"""The command line's outputs and exit codes: atomic folders with a
manifest, --out checked before computing, one-line errors with their own exit code."""
import json
import os
import pathlib

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


# -- interrupts: Ctrl-C (SIGINT) and SIGTERM in a real process ---------------------------------------

def _interrupt_when_computing(tmp_path, signum, *args):
    """Runs ``python -m delayed_ilqr.cli ARGS --out tmp_path/out`` in a process of its own, sends
    ``signum`` as soon as its staging folder exists (it is computing), and returns (exit code,
    stderr)."""
    import subprocess
    import sys
    import time
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(pathlib.Path(cli.__file__).parents[2]),
                                                                     os.environ.get("PYTHONPATH")) if p))
    process = subprocess.Popen([sys.executable, "-m", "delayed_ilqr.cli", "--no-cache", *map(str, args),
                                "--out", str(tmp_path / "out")],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not any(p.name.startswith(".out.partial") for p in tmp_path.iterdir()):
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.05)
    process.send_signal(signum)
    _, err = process.communicate(timeout=120)
    return process.returncode, err


@pytest.mark.parametrize("signum, code", [("SIGINT", 130), ("SIGTERM", 143)])
def test_an_interrupt_exits_cleanly_with_its_code_and_writes_nothing(tmp_path, signum, code):
    """Ctrl-C or SIGTERM while computing: no crash (no segfault at teardown, no traceback, no
    "Aborted!" with the exit code of a solve that did not converge), the documented exit code
    128 + signal, a message that nothing was written, and no staging folder or --out left."""
    import signal
    rc, err = _interrupt_when_computing(tmp_path, getattr(signal, signum), "compare", "point_mass", "--delays",
                                        "0,0.03", "--trials", "8")
    assert rc == code, err
    assert f"interrupted by {signum}" in err and "nothing was written" in err, err
    assert "Traceback" not in err and "Aborted" not in err and "results are still written" not in err
    assert list(tmp_path.iterdir()) == []


def test_an_interrupt_while_jax_is_imported_exits_130_without_a_traceback():
    """Ctrl-C in the seconds the console script spends importing the library (JAX with it), before
    the command line handles interrupts: one line and exit code 130, no traceback. The process
    sends itself SIGINT when the import reaches ``jax``, so the signal lands inside the import."""
    import subprocess
    import sys
    # Ctrl-C as a terminal delivers it: Python's own handler (a process started from one whose
    # SIGINT is ignored, e.g. a test runner's worker, inherits the ignoring)
    launch = ("import builtins, os, signal, sys\n"
              "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
              "real = builtins.__import__\n"
              "def hooked(name, *args, **kwargs):\n"
              "    if name == 'jax':\n"
              "        os.kill(os.getpid(), signal.SIGINT)\n"
              "    return real(name, *args, **kwargs)\n"
              "builtins.__import__ = hooked\n"
              "sys.argv = ['delayed-ilqr', 'models']\n"
              "from delayed_ilqr_entry import main\n"
              "main()\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(pathlib.Path(cli.__file__).parents[2]),
                                                                     os.environ.get("PYTHONPATH")) if p))
    done = subprocess.run([sys.executable, "-c", launch], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 130, done.stderr
    assert "interrupted by SIGINT while starting" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert done.stdout == ""             # the command did not run


def test_the_console_script_is_the_entry_that_catches_that_interrupt():
    import signal
    import tomllib
    import delayed_ilqr_entry
    from delayed_ilqr.cli import interrupts
    project = tomllib.loads((pathlib.Path(cli.__file__).parents[3] / "pyproject.toml").read_text())
    assert project["project"]["scripts"]["delayed-ilqr"] == "delayed_ilqr_entry:main"
    assert delayed_ilqr_entry.INTERRUPTED_EXIT == interrupts.exit_code(signal.SIGINT)


def test_a_memory_refusal_names_the_trials_given_and_says_when_not_even_one_fits(monkeypatch):
    import importlib
    from delayed_ilqr.models import point_mass
    simulate_module = importlib.import_module("delayed_ilqr.simulate")
    result = invoke("perturb", "point_mass", "--trials", 10 ** 12)       # 3 sensory delays x 2 runs each
    assert result.exit_code == 2, result.output
    assert "--trials=1000000000000 trials in each of 6 runs" in result.output and "6000000000000" not in result.output
    assert "at most" in result.output and "per run" in result.output
    per_trial = simulate_module.memory_estimate(point_mass(noise=True), 1)
    monkeypatch.setattr(simulate_module, "_available_memory", lambda: (per_trial, "of this machine"))     # half a trial fits
    with pytest.raises(ValueError, match="even one trial would not fit") as info:
        simulate_module.check_memory(point_mass(noise=True), 5)
    assert "at most 1 trials" not in str(info.value)


@pytest.mark.parametrize("where", ["gc callback", "__del__"])
def test_an_interrupt_that_lands_where_python_drops_exceptions_is_not_lost(where):
    """Python drops an exception raised in a gc callback (JAX has one), a weakref callback or a
    __del__ ("Exception ignored in ..."): a Ctrl-C whose handler runs there is raised again just
    after, in the command."""
    import gc
    import signal
    import time
    from delayed_ilqr.cli import interrupts

    fired = []

    def interrupt(*args):
        if not fired:
            fired.append(1)
            signal.raise_signal(signal.SIGINT)

    class Finalised:
        def __del__(self):
            interrupt()

    if where == "gc callback":
        gc.callbacks.append(interrupt)
    try:
        with pytest.raises(interrupts.Interrupted):
            with interrupts.handled():
                gc.collect() if where == "gc callback" else Finalised()
                deadline = time.monotonic() + 5
                while time.monotonic() < deadline:
                    time.sleep(0.01)
    finally:
        if interrupt in gc.callbacks:
            gc.callbacks.remove(interrupt)
    assert fired


def test_an_interrupt_during_the_final_renames_does_not_cut_them(tmp_path, monkeypatch):
    """Ctrl-C between moving the old --out aside and moving the new one in would leave neither:
    the renames finish, and the command then stops with 130, saying the results were written."""
    import signal
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    real = pathlib.Path.rename

    def interrupted_rename(self, target):
        if self == out:                                   # the old folder moved aside: Ctrl-C now
            signal.raise_signal(signal.SIGINT)
        return real(self, target)

    monkeypatch.setattr(pathlib.Path, "rename", interrupted_rename)
    result = invoke("solve", "point_mass", "--delay", "0.03", "--out", out, "--overwrite")
    assert result.exit_code == 130, result.output
    assert f"interrupted by SIGINT after the results were written to {out}" in result.output
    assert (out / "solution.npz").exists() and not (out / "old.txt").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
