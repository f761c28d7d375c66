"""Atomic file writes: a file under its final name is complete (the old one or the new one),
never a part of either, whatever interrupts the writer.

:func:`atomic_path` gives a temporary file in the target's folder (so the rename stays on
one file system) for a writer that takes a path; when the ``with`` block ends the file is
flushed to disk (``os.fsync``) and renamed over the target (``os.replace``, atomic on POSIX
and Windows). :func:`atomic_write` does the same for a file handle, :func:`write_text_atomic`
for a string, :func:`~jaxrefl.io.save_npz_atomic` for a NumPy archive.

An exception inside the ``with`` block removes the temporary file and leaves the target as
it was; a process killed mid-write leaves at most a hidden ``.<name>.<pid>-<random>.tmp``
beside it. The temporary name is unique to the call (created exclusively), so concurrent
writers never share one; it is created with the permissions of the existing target, or of
the umask for a new one. An error creating it names the target, not the temporary file.
"""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any, Literal

__all__ = ["atomic_path", "atomic_write", "write_text_atomic"]


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path to write ``path`` through, atomically (module docstring)."""
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(2, f"no directory {path.parent} to write {path.name} in", str(path))
    tmp = path.parent / f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp"
    try:
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))  # umask applies
    except OSError as e:  # the error names the file asked for, not the temporary one
        raise type(e)(
            e.errno, f"cannot write {path.name} in {path.parent}: {e.strerror}", str(path)
        ) from None
    try:
        if path.exists():
            os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_write(path: str | Path, mode: Literal["w", "wb"] = "wb") -> Iterator[IO[Any]]:
    """A handle to write ``path`` through, atomically (module docstring); ``mode`` is
    ``"wb"`` (bytes) or ``"w"`` (UTF-8 text)."""
    with atomic_path(path) as tmp, open(tmp, mode, encoding=None if "b" in mode else "utf-8") as fh:
        yield fh


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (module docstring); returns the path."""
    with atomic_write(path, "w") as fh:
        fh.write(text)
    return Path(path)
