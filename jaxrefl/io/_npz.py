"""Atomic NumPy archives: a resumable job's pieces (tiles, MCMC chunks) are complete or absent.

:func:`save_npz_atomic` writes the archive through :func:`~jaxrefl.io.atomic_write`, so an
interrupted run never leaves a truncated archive under the final name.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ._atomic import atomic_write

__all__ = ["save_npz_atomic"]


def save_npz_atomic(path: str | Path, **arrays: Any) -> None:
    """Write ``arrays`` to ``path`` as an uncompressed ``.npz``, atomically (module docstring)."""
    with atomic_write(path) as fh:
        np.savez(fh, **arrays)
