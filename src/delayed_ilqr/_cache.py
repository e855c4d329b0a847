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

Several processes may share the folder (the sweep's Dask workers, two commands at once): JAX's own
file cache writes an entry in place, without a lock, so a process reading it meanwhile meets half
a file (JAX warns and compiles again), and a process killed while writing leaves a truncated entry
that every later process fails to read and, the name being taken, never replaces. Here each entry
is written whole into a hidden temporary file of the folder and then given its name by a hard
link (`AtomicFileCache`): a name always holds a complete entry, the first complete writer of a key
wins, and a killed writer leaves only a hidden ``.partial`` file that JAX never reads.
"""
from __future__ import annotations

import contextlib
import os
import pathlib
import tempfile
from functools import cache
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
    if jax.config.jax_compilation_cache_dir is not None:
        cc.reset_cache()        # JAX opens its cache folder once; a new one (or ours) needs a new cache
    cc.set_cache_dir(str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    # every entry, however small (JAX's default 0 lets it pick a filesystem-dependent minimum)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    _install(folder)
    return folder


@cache
def _file_cache_class():
    """`AtomicFileCache`, built on JAX's file cache (a class of JAX's internals, so built when the
    cache is turned on, not when the library is imported)."""
    from jax._src import lru_cache

    class AtomicFileCache(lru_cache.LRUCache):
        """JAX's file cache, whose entries are written whole under a temporary name and then linked
        to their own (module docstring). Reading is JAX's. With a size limit
        (``jax_compilation_cache_max_size``) JAX's own locked writes are kept."""

        def put(self, key: str, value: bytes) -> None:
            if self.eviction_enabled:
                return super().put(key, value)
            if not key:
                raise ValueError("key cannot be empty")
            target = self.path / f"{key}{lru_cache._CACHE_SUFFIX}"
            if target.exists():
                return
            handle, staged = tempfile.mkstemp(dir=self.path, prefix=f".{key}.", suffix=".partial")
            try:
                with os.fdopen(handle, "wb") as file:
                    file.write(value)
                try:
                    os.link(staged, target)     # fails if another process gave the name first: theirs stays
                except FileExistsError:
                    pass
                except OSError:                 # a file system without hard links: renamed over, whole
                    os.replace(staged, target)
            finally:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(staged)

    return AtomicFileCache


def _install(folder: pathlib.Path) -> None:
    """Makes JAX's persistent cache of this process an `AtomicFileCache` in ``folder`` (JAX opens
    its cache at the first compilation after ``set_cache_dir``; here it is opened now, with ours)."""
    import jax
    from jax._src import compilation_cache as jax_cache

    if jax.config.jax_compilation_cache_check_contents:
        return                  # JAX's verifying wrapper around its own cache: left as JAX builds it
    with jax_cache._cache_initialized_mutex:
        jax_cache._cache = _file_cache_class()(str(folder), max_size=jax.config.jax_compilation_cache_max_size)
        jax_cache._cache_initialized = True

