"""Atomic NumPy archives: a resumable job's pieces (tiles, MCMC chunks) are complete or absent.

:func:`save_npz_atomic` writes to a temporary file in the same folder, flushes it to disk
and renames it over the target (``os.replace`` is atomic on POSIX and Windows), so an
interrupted run never leaves a truncated archive under the final name.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["save_npz_atomic"]


def save_npz_atomic(path: str | Path, **arrays: Any) -> None:
    """Write ``arrays`` to ``path`` as an uncompressed ``.npz``, atomically (module docstring)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
