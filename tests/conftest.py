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


@pytest.fixture(autouse=True, scope="session")
def _compilation_cache(tmp_path_factory):
    """JAX's persistent compilation cache, in a temporary folder of this test process: the
    executables released after each file (below) are read back from disk when a later file
    compiles the same program (the common problems recur in many files), instead of compiled
    again. test_sweep.py moves it to its own folder for its module and restores it."""
    delayed_ilqr.enable_compilation_cache(tmp_path_factory.mktemp("jax-cache"))
    yield


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_executables():
    """Each test file compiles hundreds of solvers, and XLA's CPU executables stay loaded in the
    process until JAX's caches are cleared. The whole suite in one process died, at the same test
    each time, with a segmentation fault inside an XLA compile that the test alone does not
    have; clearing after each file bounds what one process holds."""
    yield
    jax.clear_caches()
