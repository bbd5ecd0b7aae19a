"""Atomic file writing: a file appears under its final name complete, or not at all.

Every writer in bubsub writes to a temporary file in the destination's own
directory (so the final rename never crosses a file system), flushes it to
disk, and then renames it over the destination with :func:`os.replace`, which
is atomic on POSIX and Windows. If anything fails on the way, the temporary
file is removed and the destination is left untouched (an older file under
that name survives unchanged).

Examples
--------
>>> with atomic_path("result.h5") as tmp:      # doctest: +SKIP
...     h5py.File(tmp, "w").close()
>>> atomic_write_text("table.csv", "id,area\\n")  # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

__all__ = ["atomic_path", "atomic_open", "atomic_write_text", "atomic_write_bytes"]


def _umask():
    # os.umask can only be read by setting it; put it straight back.
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _destination(path):
    if isinstance(path, (bytes, bytearray)):
        path = os.fsdecode(path)
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    p = Path(path)
    if str(p) == "" or p.name in ("", ".", ".."):
        raise ValueError(f"path {str(path)!r} does not name a file")
    if p.is_dir():
        raise ValueError(f"path {str(p)!r} is a directory, not a file")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"directory {str(parent)!r} of {str(p)!r} does not exist")
    return p, parent


def _fsync_dir(directory):
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # e.g. Windows: directories cannot be opened
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path, *, fsync=True):
    """Yield a temporary path to write; rename it to ``path`` on success.

    The temporary file is created (empty) in the same directory as ``path``,
    with a hidden name ``.<name>.<random>.tmp``. When the ``with`` block
    ends without an exception, the temporary file is flushed to disk and
    renamed over ``path``; if the block raises (or the temporary file was
    deleted by the block), the temporary file is removed, ``path`` is not
    touched, and the exception propagates.

    Parameters
    ----------
    path : str or os.PathLike
        Final destination. Its directory must exist.
    fsync : bool
        Flush the file (and the directory entry) to disk before/after the
        rename, so that a crash cannot leave an empty file under ``path``.

    Yields
    ------
    pathlib.Path
        The temporary file to write (may be reopened and truncated freely).

    Raises
    ------
    ValueError
        If ``path`` is a directory or its directory does not exist.
    """
    dest, parent = _destination(path)
    fd, tmp_name = tempfile.mkstemp(dir=parent, prefix=f".{dest.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f"temporary file {tmp} for {dest} vanished before the rename")
        # mkstemp makes 0600 files; give the result the usual permissions.
        os.chmod(tmp, 0o666 & ~_umask())
        if fsync:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp, dest)
        if fsync:
            _fsync_dir(parent)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


@contextlib.contextmanager
def atomic_open(path, mode="w", *, encoding="utf-8", newline=None, fsync=True):
    """Open a file object for writing that is renamed to ``path`` on success.

    Parameters
    ----------
    path : str or os.PathLike
    mode : {"w", "wb", "wt", "x", "xb", "xt"}
        Write mode. With ``"x"`` the call fails if ``path`` already exists
        (checked up front; the rename itself overwrites).
    encoding, newline : str, optional
        Text-mode options (ignored in binary mode).
    fsync : bool
        See :func:`atomic_path`.

    Yields
    ------
    file object
    """
    if mode not in ("w", "wb", "wt", "x", "xb", "xt"):
        raise ValueError(f"mode must be a write mode ('w', 'wb', 'wt', 'x', 'xb', 'xt'), got {mode!r}")
    if mode.startswith("x") and Path(path).exists():
        raise FileExistsError(f"{path} already exists")
    binary = "b" in mode
    with atomic_path(path, fsync=fsync) as tmp:
        if binary:
            fh = open(tmp, "wb")
        else:
            fh = open(tmp, "w", encoding=encoding, newline=newline)
        with fh:
            yield fh


def atomic_write_text(path, text, *, encoding="utf-8", newline=None):
    """Write ``text`` to ``path`` atomically. Returns the destination :class:`Path`."""
    if not isinstance(text, str):
        raise ValueError(f"text must be a str, got {type(text).__name__}")
    with atomic_open(path, "w", encoding=encoding, newline=newline) as fh:
        fh.write(text)
    return Path(path)


def atomic_write_bytes(path, data):
    """Write ``data`` (bytes-like) to ``path`` atomically. Returns the destination :class:`Path`."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ValueError(f"data must be bytes-like, got {type(data).__name__}")
    with atomic_open(path, "wb") as fh:
        fh.write(data)
    return Path(path)
