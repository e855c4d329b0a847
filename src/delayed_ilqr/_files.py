"""The files the library writes and reads.

Writes are atomic: the content goes to a hidden temporary file beside the target, is flushed to
disk, and is renamed over the target (``os.replace``, atomic on POSIX and Windows), so that a
process killed or interrupted mid-write leaves the old file (or none), never a truncated one.
Every writer of the library (saved solutions, sweep stores' metadata, the command line's JSON,
markdown, NPZ files and figures) goes through `atomic_file`.

Reads that fail raise `FileFormatError`, a ``ValueError`` whose message names the file,
what it should be and what is wrong with it, whatever the underlying library raised
(``zipfile``, ``json``, NumPy's pickle refusal, a missing entry, ...).
"""
from __future__ import annotations

import contextlib
import json
import os
import pathlib
import secrets
import zipfile
from typing import Iterator

import numpy as np

__all__ = ["FileFormatError", "atomic_file", "write_text", "write_json", "savez", "save_figure", "open_npz",
           "read_entry", "read_json", "parse_json"]


class FileFormatError(ValueError):
    """A file that cannot be read as what it should be; ``path`` is the file."""

    def __init__(self, path, what: str):
        self.path = path
        super().__init__(f"{os.fspath(path)}: {what}")


@contextlib.contextmanager
def atomic_file(path, mode: str = "wb") -> Iterator:
    """Yields a file object open for writing (``mode`` "wb" or "w"); when the block ends normally
    the content replaces ``path`` whole, else (an exception, KeyboardInterrupt included) the
    temporary file is removed and ``path`` is untouched."""
    path = pathlib.Path(path)
    tmp = path.parent / f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp"
    # 0o666 less the umask, as open() gives a new file (tempfile.mkstemp would make it private)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _sync_folder(path.parent)


def _sync_folder(folder: pathlib.Path) -> None:
    """The rename itself on disk (POSIX; a no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_text(path, text: str) -> None:
    """``text`` (UTF-8) written atomically to ``path``."""
    with atomic_file(path, "wb") as f:
        f.write(text.encode())


def write_json(path, data, **kwargs) -> None:
    """Strict JSON (``allow_nan=False``, indented) written atomically to ``path``."""
    write_text(path, json.dumps(data, indent=2, allow_nan=False, **kwargs) + "\n")


def savez(path, arrays: dict, compressed: bool = False) -> None:
    """An NPZ file of ``arrays`` written atomically to ``path`` (exactly that name: no ``.npz``
    appended)."""
    with atomic_file(path, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)


def save_figure(figure, path, **kwargs) -> None:
    """A matplotlib figure written atomically to ``path``, in the format of its suffix."""
    path = pathlib.Path(path)
    with atomic_file(path, "wb") as f:
        figure.savefig(f, format=path.suffix.lstrip(".") or None, **kwargs)


def open_npz(path, what: str) -> "np.lib.npyio.NpzFile":
    """``path`` opened as an NPZ archive of arrays (``allow_pickle=False``: nothing in it runs);
    ``what`` says what the file should be (e.g. "a delayed-ilqr file (delayed_ilqr.save writes
    one)"). Use as a context manager. Raises `FileFormatError` for a missing file, a
    folder, a single ``.npy`` array, a text or pickle file, an empty, truncated or damaged archive."""
    path = pathlib.Path(path)
    if not path.exists():
        raise FileFormatError(path, f"no such file; expected {what}")
    if path.is_dir():
        raise FileFormatError(path, f"is a folder; expected {what}")
    if path.stat().st_size == 0:
        raise FileFormatError(path, f"is empty; expected {what}")
    try:
        with open(path, "rb") as f:
            start = f.read(6)
    except OSError as exc:
        raise FileFormatError(path, f"cannot be read ({_reason(exc)}); expected {what}") from None
    if start.startswith(b"\x93NUMPY"):
        raise FileFormatError(path, f"is a single NumPy array (an .npy file), not an NPZ archive; expected {what}")
    if not start.startswith(b"PK"):
        raise FileFormatError(path, f"is not an NPZ archive (it starts with {start!r}, not a zip archive's "
                                    f"b'PK'); expected {what}")
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, UnicodeError) as exc:
        raise FileFormatError(path, f"is not a readable NPZ archive ({_reason(exc)}); expected {what}") from None


def read_entry(npz, name: str, path, what: str) -> np.ndarray:
    """The array ``name`` of an open NPZ archive; a damaged entry (truncated, bad CRC, pickled
    object) is a `FileFormatError` naming it."""
    try:
        return npz[name]
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, UnicodeError, KeyError) as exc:
        raise FileFormatError(path, f"its entry {name!r} cannot be read ({_reason(exc)}); expected {what}") from None


def read_json(path, what: str):
    """The JSON value of the file ``path``; a missing, unreadable, non-UTF-8 or malformed file is
    a `FileFormatError` saying ``what`` it should be."""
    path = pathlib.Path(path)
    try:
        text = path.read_bytes().decode()
    except FileNotFoundError:
        raise FileFormatError(path, f"no such file; expected {what}") from None
    except (OSError, UnicodeError) as exc:
        raise FileFormatError(path, f"cannot be read as text ({_reason(exc)}); expected {what}") from None
    return parse_json(text, path, what)


def parse_json(text: str, path, what: str, part: str = ""):
    """``text`` (the content of ``path``, or of its ``part`` such as "its header") parsed as
    JSON, or a `FileFormatError`."""
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise FileFormatError(path, f"{part + ' ' if part else ''}is not valid JSON ({_reason(exc)}); "
                                    f"expected {what}") from None


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
