"""Shared test configuration: float64 JAX, XLA's CPU flags and a reproducible, time-bounded
hypothesis profile."""
import os

# One OpenBLAS thread for SciPy (read when SciPy's OpenBLAS loads, which comes later than this
# file): the reference L-BFGS-B (tests/direct.py, experiments/fitting.py) works on vectors of a few
# hundred entries, where OpenBLAS's worker threads only wait for each other, and under `make test`'s
# two workers on two cores they spin against XLA's threads (docs/performance.md, "Test-suite
# time"). The xdist workers start after this file runs, so NumPy's OpenBLAS gets it there too.
# setdefault: a run that sets its own count keeps it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

import delayed_ilqr  # noqa: E402

# what a program using the library does first; the suite's speed depends on the flags (their
# effect is checked in test_xla_options.py), and they must be set before any JAX computation
jax.config.update("jax_enable_x64", True)
delayed_ilqr.configure_cpu()

# the command line turns JAX's persistent compilation cache on by default; the in-process CLI tests
# must not write into the user's cache folder (tests/test_compilation_cache.py turns it on in
# subprocesses, with a temporary folder)
os.environ.setdefault("DELAYED_ILQR_NO_CACHE", "1")

from hypothesis import HealthCheck, settings  # noqa: E402

# Every distinct array shape recompiles the jitted solvers (about a second each on a small CPU),
# so the example count is kept modest; derandomize makes every run draw the same examples.
settings.register_profile(
    "ci",
    deadline=None,
    max_examples=25,
    derandomize=True,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
# A heavier profile for occasional local runs: HYPOTHESIS_PROFILE=thorough make test
settings.register_profile("thorough", parent=settings.get_profile("ci"), max_examples=200)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


import pytest  # noqa: E402


def _link_missing(source, target):
    """Hard-links into ``target`` every cache entry of ``source`` that ``target`` lacks.

    A link names a file that is already whole, in one atomic step (a name that exists is left
    alone), and JAX never rewrites an entry it has written; so a reader of either folder sees an
    entry complete or not at all. JAX's own folder cache writes without a lock (a concurrent
    reader could meet a half-written file), which is why the workers never share one folder."""
    for name in {n for n in os.listdir(source) if n.endswith("-cache")} - set(os.listdir(target)):
        try:
            os.link(os.path.join(source, name), os.path.join(target, name))
        except FileExistsError:
            pass
        except OSError:         # a file system without hard links: the entry is compiled again
            return


@pytest.fixture(autouse=True, scope="session")
def _compilation_cache(tmp_path_factory):
    """JAX's persistent compilation cache, in a temporary folder of this test process: the
    executables released after each file (below) are read back from disk when a later file
    compiles the same program (the common problems recur in many files), instead of compiled
    again. test_sweep.py moves it to its own folder for its module and restores it.

    Under xdist the workers also pass their entries to each other through a folder of the run
    (``_share_compilations``): returns (own folder, shared folder or None)."""
    own = delayed_ilqr.enable_compilation_cache(tmp_path_factory.mktemp("jax-cache"))
    shared = None
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # JAX's default also turns on XLA's GPU autotuning cache in a subfolder, whose path enters
        # every key: the workers' folders differ, so their keys would never match. On the CPU
        # there is nothing to autotune.
        jax.config.update("jax_persistent_cache_enable_xla_caches", "none")
        # a worker's base folder is <the run's base folder>/<worker id>: the parent is the run's
        shared = tmp_path_factory.getbasetemp().parent / "jax-cache-shared"
        shared.mkdir(exist_ok=True)
    yield own, shared


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_executables():
    """Each test file compiles hundreds of solvers, and XLA's CPU executables stay loaded in the
    process until JAX's caches are cleared. The whole suite in one process died, at the same test
    each time, with a segmentation fault inside an XLA compile that the test alone does not
    have; clearing after each file bounds what one process holds."""
    yield
    jax.clear_caches()


@pytest.fixture(autouse=True)
def _share_compilations(_compilation_cache):
    """Under xdist, between tests (when this process compiles nothing) the worker takes the other
    worker's new cache entries into its own folder and gives its own to the shared folder, so that
    a program is compiled once per run rather than once per worker (``_link_missing``)."""
    own, shared = _compilation_cache
    if shared is None:
        yield
        return
    _link_missing(shared, own)
    yield
    _link_missing(own, shared)


# The files that take longest, handed out first (the measurements: docs/performance.md, "Test-suite
# time"). `make test` gives whole files to its two workers in collection order (--dist loadfile
# --no-loadscope-reorder); a long file started last would leave one worker running it alone at the
# end, as xdist's own order (files with the most tests first) did with these, which hold few tests.
LONGEST_FIRST = (
    "test_center_out.py",
    "test_convergence.py",
    "test_limits_family.py",
    "test_gradients.py",
    "test_mpc.py",
    "test_gallery.py",
    "test_human_reaches.py",
    "test_gradients_muscle.py",
    "test_continuation.py",
    "test_reach_shape.py",
    "test_time.py",
    "test_limits.py",
    "test_fitting.py",
    "test_alternation.py",
    "test_convergence_muscle.py",
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))    # stable: the rest keep their order
