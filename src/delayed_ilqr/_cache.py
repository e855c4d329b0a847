"""JAX's persistent compilation cache, opt-in: [`enable_compilation_cache`][delayed_ilqr.enable_compilation_cache].

A solve takes about a millisecond and its compilation about a second, and every new static
structure (model, sizes, delay) compiles again, in every new process. JAX can keep the compiled
executables on disk, keyed by the program, the compile options, XLA's flags (so the flags of
[`configure_cpu`][delayed_ilqr.configure_cpu] are part of the key), the backend and the jax version; a
second process that compiles the same solver reads it back instead (docs/performance.md#compilation-cache).

Importing ``delayed_ilqr`` sets nothing: the cache is a process-wide JAX setting, the program's to
choose. A program turns it on with one call; the ``delayed-ilqr`` command line does so by default
(``--no-cache`` or ``DELAYED_ILQR_NO_CACHE=1`` turn it off, ``--cache-dir`` or
``DELAYED_ILQR_CACHE_DIR`` move it), and so do the sweep's Dask workers.

The folder: ``path``, else ``$DELAYED_ILQR_CACHE_DIR``, else ``jax`` in the user's cache folder
(``platformdirs.user_cache_dir("delayed-ilqr")``: ``~/.cache/delayed-ilqr/jax`` on Linux, or under
``$XDG_CACHE_HOME``; ``~/Library/Caches/delayed-ilqr/jax`` on macOS). The cache is trusted code:
do not point it at a folder others can write to.
"""
from __future__ import annotations

import os
import pathlib
from typing import Optional

__all__ = ["enable_compilation_cache", "default_cache_dir", "CACHE_DIR_ENV", "NO_CACHE_ENV",
           "MIN_COMPILE_SECONDS"]

CACHE_DIR_ENV = "DELAYED_ILQR_CACHE_DIR"
NO_CACHE_ENV = "DELAYED_ILQR_NO_CACHE"

# Every compilation is written, also the small programs of eager jax.numpy calls: a process
# compiles dozens of them, together about as long as the solver, and reading a file back is far
# cheaper (a threshold of 0.1 s, or JAX's default of 1 s, keeps only the solver:
# docs/performance.md#compilation-cache).
MIN_COMPILE_SECONDS = 0.0


def default_cache_dir() -> pathlib.Path:
    """The cache folder used when none is given: ``$DELAYED_ILQR_CACHE_DIR``, else ``jax`` in
    ``platformdirs.user_cache_dir("delayed-ilqr")``."""
    explicit = os.environ.get(CACHE_DIR_ENV)
    if explicit:
        return pathlib.Path(explicit).expanduser()
    import platformdirs
    return pathlib.Path(platformdirs.user_cache_dir("delayed-ilqr", appauthor=False)) / "jax"


def enable_compilation_cache(path: Optional[os.PathLike | str] = None,
                             min_compile_seconds: float = MIN_COMPILE_SECONDS) -> pathlib.Path:
    """Turns on JAX's persistent compilation cache for this process, in ``path``.

    Call it early (before the first solve whose compilation should be kept; it may also come
    later, and then applies to the compilations that follow). Calling it again with another
    folder moves the cache there.

    Args:
        path: the cache folder (created if missing); default [`default_cache_dir`][delayed_ilqr.default_cache_dir].
        min_compile_seconds: compilations shorter than this are not written
            (``jax_persistent_cache_min_compile_time_secs``); 0 writes every one.

    Returns:
        The absolute cache folder.

    Raises:
        ValueError: when ``path`` cannot be created, or ``min_compile_seconds`` is negative.
    """
    import jax
    from jax.experimental.compilation_cache import compilation_cache as cc

    if not (isinstance(min_compile_seconds, (int, float)) and min_compile_seconds >= 0):
        raise ValueError(f"min_compile_seconds must be a non-negative number; got {min_compile_seconds!r}")
    folder = (default_cache_dir() if path is None else pathlib.Path(path).expanduser()).absolute()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"path must be a folder that can be created; cannot create {folder}: "
                         f"{exc.strerror or exc}") from None
    if jax.config.jax_compilation_cache_dir not in (None, str(folder)):
        cc.reset_cache()        # JAX opens its cache folder once; another folder needs a new cache
    cc.set_cache_dir(str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    # every entry, however small (JAX's default 0 lets it pick a filesystem-dependent minimum)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return folder

