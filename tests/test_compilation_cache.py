"""JAX's persistent compilation cache: opt-in for the library (:func:`delayed_ilqr.enable_compilation_cache`),
on by default for the command line (``--no-cache``, ``DELAYED_ILQR_NO_CACHE`` and ``--cache-dir``).
Each check runs in fresh processes with a temporary cache folder: the cache is process-wide."""
import json
import os
import subprocess
import sys
import textwrap

import pytest

# counts JAX's compile requests that went through the persistent cache, and those it answered
_COUNTING_CLI = r"""
import atexit, collections, json, sys
import jax.monitoring
counts, path = collections.Counter(), sys.argv[1]
jax.monitoring.register_event_listener(lambda event, **kw: counts.update([event]))
def dump():
    with open(path, "w") as f:
        f.write(json.dumps(counts))
atexit.register(dump)
sys.argv = ["delayed-ilqr"] + sys.argv[2:]
from delayed_ilqr.cli import main
main()
"""
REQUESTS, HITS = "/jax/compilation_cache/compile_requests_use_cache", "/jax/compilation_cache/cache_hits"


def fresh_env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("XLA_FLAGS", "DELAYED_ILQR_NO_CACHE", "DELAYED_ILQR_CACHE_DIR")}
    env["PYTHONPATH"] = os.pathsep.join(sys.path)
    env.update(extra)
    return env


def cli_counts(tmp_path, name, args, env) -> dict:
    out = tmp_path / f"{name}.json"
    result = subprocess.run([sys.executable, "-c", _COUNTING_CLI, str(out), *args], env=env, capture_output=True,
                            text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr
    return json.loads(out.read_text())


def test_the_command_line_caches_by_default_and_a_second_process_compiles_nothing(tmp_path):
    cache = tmp_path / "cache"
    env = fresh_env(DELAYED_ILQR_CACHE_DIR=str(cache))
    solve = ["solve", "point_mass", "--delay", "0.03"]
    first = cli_counts(tmp_path, "first", solve, env)
    entries = sorted(os.listdir(cache))
    assert first.get(REQUESTS, 0) > 0 and first.get(HITS, 0) == 0
    assert any(e.startswith("jit__solve_body") for e in entries)      # the solver itself is kept
    second = cli_counts(tmp_path, "second", solve, env)
    # every compilation of the second process was read from the cache, and nothing new was written
    assert second[HITS] == second[REQUESTS] == first[REQUESTS]
    assert sorted(os.listdir(cache)) == entries


@pytest.mark.parametrize("args, env, expected", [
    ([], {}, [None]),                                            # on by default, in the default folder
    (["--cache-dir", "somewhere"], {}, ["somewhere"]),
    ([], {"DELAYED_ILQR_CACHE_DIR": "there"}, ["there"]),
    (["--no-cache"], {}, []),
    ([], {"DELAYED_ILQR_NO_CACHE": "1"}, []),
    (["--no-cache", "--cache-dir", "somewhere"], {}, []),
])
def test_the_command_line_options_and_environment_variables(monkeypatch, args, env, expected):
    from click.testing import CliRunner
    from delayed_ilqr import cli
    calls = []
    monkeypatch.setattr(cli, "enable_compilation_cache", lambda path: calls.append(path))
    monkeypatch.delenv("DELAYED_ILQR_NO_CACHE", raising=False)
    monkeypatch.delenv("DELAYED_ILQR_CACHE_DIR", raising=False)
    result = CliRunner().invoke(cli.main, [*args, "models"], env=env, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert [None if c is None else str(c) for c in calls] == expected

def test_enable_compilation_cache_sets_the_folder_moves_it_and_refuses_a_bad_one(tmp_path):
    code = textwrap.dedent("""
        import json, sys, jax, jax.numpy as jnp, os
        import delayed_ilqr
        a, b, bad = sys.argv[1:4]
        before = jax.config.jax_compilation_cache_dir
        first = delayed_ilqr.enable_compilation_cache(a)
        jax.jit(lambda x: jnp.sin(x) * 2)(1.0).block_until_ready()
        second = delayed_ilqr.enable_compilation_cache(b)
        jax.jit(lambda x: jnp.cos(x) * 3)(1.0).block_until_ready()
        try:
            delayed_ilqr.enable_compilation_cache(bad)
            error = None
        except ValueError as exc:
            error = str(exc)
        print(json.dumps(dict(before=before, first=str(first), second=str(second), a=os.listdir(a),
                              b=os.listdir(b), error=error)))
    """)
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    a, b = tmp_path / "a", tmp_path / "b"
    result = subprocess.run([sys.executable, "-c", code, str(a), str(b), str(blocker / "sub")], env=fresh_env(),
                            capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout.strip().splitlines()[-1])
    assert out["before"] is None and out["first"] == str(a) and out["second"] == str(b)
    assert len(out["a"]) == 1 and len(out["b"]) == 1 and out["a"] != out["b"]   # one program each
    assert out["error"].startswith("path must be a folder that can be created")


def test_the_default_folder_follows_the_environment(monkeypatch, tmp_path):
    from delayed_ilqr import default_cache_dir
    monkeypatch.setenv("DELAYED_ILQR_CACHE_DIR", str(tmp_path / "here"))
    assert default_cache_dir() == tmp_path / "here"
    monkeypatch.delenv("DELAYED_ILQR_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):
        assert default_cache_dir() == tmp_path / "xdg" / "delayed-ilqr" / "jax"
    else:
        pytest.skip("XDG_CACHE_HOME is the Linux convention")


# compiles PROGRAMS small programs (each its own constant) with the cache in argv[1]; argv[2] "kill"
# makes the process kill itself (SIGKILL) halfway through writing its first cache entry; prints the
# counts of cache requests and hits as JSON. A cache entry that cannot be read is an error.
_COMPILING = r"""
import collections, json, os, signal, sys
import jax, jax.numpy as jnp, jax.monitoring
import delayed_ilqr
jax.config.update("jax_raise_persistent_cache_errors", True)
counts = collections.Counter()
jax.monitoring.register_event_listener(lambda event, **kw: counts.update([event]))
delayed_ilqr.enable_compilation_cache(sys.argv[1])
if sys.argv[2] == "kill":
    real = os.fdopen
    class HalfThenKilled:
        def __init__(self, *args, **kwargs):
            self.file = real(*args, **kwargs)
        def __enter__(self):
            return self
        def __exit__(self, *exc):
            self.file.close()
        def write(self, data):
            self.file.write(data[:len(data) // 2])
            self.file.flush()
            os.kill(os.getpid(), signal.SIGKILL)
    os.fdopen = HalfThenKilled
for k in range(PROGRAMS):
    jax.jit(lambda x: jnp.sin(x) * k + k).lower(1.0).compile()
print(json.dumps(counts))
"""
PROGRAMS = 4


def _compiling(cache, mode="run"):
    code = _COMPILING.replace("PROGRAMS", str(PROGRAMS))
    return subprocess.Popen([sys.executable, "-c", code, str(cache), mode], env=fresh_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _counts(process) -> dict:
    out, err = process.communicate(timeout=300)
    assert process.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1])


def test_processes_sharing_the_cache_folder_never_read_a_partial_entry(tmp_path):
    """The sweep's Dask workers (or two commands) share one cache folder. A process killed halfway
    through writing an entry leaves no entry under its name (JAX's own cache writes in place: the
    truncated file would fail every later read, and its name would never be written again); two
    processes writing the same entries at once leave each complete; a later process reads every one.
    Unreadable entries are errors here (jax_raise_persistent_cache_errors)."""
    cache = tmp_path / "cache"
    killed = _compiling(cache, "kill")
    killed.communicate(timeout=300)
    assert killed.returncode == -9
    assert not [p for p in os.listdir(cache) if p.endswith("-cache")]        # only the hidden partial file
    both = [_compiling(cache), _compiling(cache)]
    for counts in map(_counts, both):
        assert counts[REQUESTS] >= PROGRAMS
    entries = sorted(p for p in os.listdir(cache) if p.endswith("-cache"))
    assert len(entries) >= PROGRAMS
    later = _counts(_compiling(cache))
    assert later[HITS] == later[REQUESTS] >= PROGRAMS
    assert sorted(p for p in os.listdir(cache) if p.endswith("-cache")) == entries
