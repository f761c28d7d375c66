"""Resumable work on disk, shared by the processes of a job (:class:`WorkStore`).

A store is a folder of finished pieces of one job, each an ``.npz`` under its key, beside a
``manifest.json`` naming the job. The job is named by a JSON-able dict, its fingerprint
(the settings and data that decide every piece); the manifest records the fingerprint's
entries, its hash (:func:`fingerprint_hash`: SHA-1 of its canonical JSON) and, where given,
further entries that are written but not compared (``record``).

Opening a folder whose manifest holds another hash (another job), or cannot be read, raises
:class:`~jaxrefl._errors.JaxreflError` with one wording whatever the job, naming the entries
that differ and the way out (``--restart``, or another ``--out`` folder); ``restart=True``
deletes the pieces there and writes the manifest anew, and so does opening a folder with
no manifest (pieces without one cannot be matched to a job). A folder written before the
manifest carried the hash (no ``fingerprint`` entry) counts as another job: it is refused,
never mixed with new pieces.

Pieces are written atomically (:func:`jaxrefl.io.save_npz_atomic`): a file is complete or
absent. :meth:`WorkStore.load` reads one; a file that is absent, truncated, corrupt or fails
the caller's ``check`` reads as None, and the piece is computed again.

Several processes (:mod:`jaxrefl.fit._distributed`): every process checks the manifest (the
same files give each process the same error), process 0 alone prepares the folder while
the others wait at a barrier, and each process saves the pieces it computes. After a barrier
that every process reaches once its own pieces are written, :meth:`WorkStore.require` reads
any piece and names one still missing: the folder is not one folder shared by them all.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.io import save_npz_atomic, write_text_atomic

from ._distributed import process_barrier

__all__ = ["MANIFEST", "WorkStore", "fingerprint_hash", "refuse_other_work"]

MANIFEST = "manifest.json"
# The manifest entry holding the fingerprint's hash (module docstring).
_HASH = "fingerprint"

Arrays = dict[str, np.ndarray]


def fingerprint_hash(fingerprint: Mapping[str, Any]) -> str:
    """SHA-1 (40 hex digits) of ``fingerprint`` as canonical JSON (sorted keys, no spaces):
    the same dict gives the same hash in every process and every run."""
    text = json.dumps(fingerprint, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha1(text.encode()).hexdigest()


def _way_out(folder: Path) -> str:
    return f"use --restart to discard the work in {folder}, or another --out folder"


def _check(path: Path, fingerprint: Mapping[str, Any], digest: str) -> bool:
    """Whether the manifest ``path`` exists and names this job (False: absent); raises where
    it is unreadable or names another job (the pieces beside it are not this job's)."""
    if not path.exists():
        return False
    try:
        old = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, OSError) as e:
        raise JaxreflError(
            f"{path}: unreadable resume manifest ({e}); the work beside it cannot be matched "
            f"to this job: {_way_out(path.parent)}"
        ) from None
    if isinstance(old, dict) and old.get(_HASH) == digest:
        return True
    new = json.loads(json.dumps(fingerprint))  # as it reads back (tuples become lists)
    differ = [k for k in new if not isinstance(old, dict) or old.get(k) != new[k]]
    which = f" (it differs in: {', '.join(differ)})" if differ else ""
    raise JaxreflError(
        f"{path}: the work in {path.parent} belongs to a different job{which}; "
        f"{_way_out(path.parent)}"
    )


def refuse_other_work(folder: str | Path, entries: Mapping[str, Any]) -> None:
    """Raise :meth:`WorkStore.open`'s refusal now where ``folder``'s manifest names other
    values of some of its fingerprint's ``entries``: a job whose whole fingerprint is known
    only after costly steps (a model chosen by held-out photos) is refused before them.
    Nothing is raised where the folder has no readable manifest or the entries agree; the
    store's own check at :meth:`WorkStore.open` still holds."""
    path = Path(folder) / MANIFEST
    try:
        old = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return
    new = json.loads(json.dumps(dict(entries)))  # as it reads back (tuples become lists)
    differ = [k for k in new if not isinstance(old, dict) or old.get(k) != new[k]]
    if differ:
        raise JaxreflError(
            f"{path}: the work in {path.parent} belongs to a different job (it differs in: "
            f"{', '.join(differ)}); {_way_out(path.parent)}"
        )


class WorkStore:
    """The finished pieces of one job in ``folder`` (module docstring); open one with
    :meth:`open`."""

    def __init__(self, folder: Path, digest: str):
        self.folder = folder
        self.digest = digest

    @classmethod
    def open(
        cls,
        folder: str | Path,
        fingerprint: Mapping[str, Any],
        restart: bool = False,
        *,
        record: Mapping[str, Any] | None = None,
        job: str = "jaxrefl",
    ) -> WorkStore:
        """``folder`` prepared for the job named by ``fingerprint`` (module docstring):
        checked against its manifest, or cleared and given a new one (``restart``, or no
        manifest yet). ``record``: manifest entries beside the fingerprint's, not compared.
        ``job`` names the barrier of a job of several processes (``"<job>: folder
        prepared"``), the same in every process."""
        folder = Path(folder)
        record = dict(record or {})
        if _HASH in fingerprint or set(record) & set(fingerprint):
            raise JaxreflError(
                f"a work store's fingerprint and record share entries, or use {_HASH!r}: "
                f"{sorted(fingerprint)}, {sorted(record)}"
            )
        digest = fingerprint_hash(fingerprint)
        store = cls(folder, digest)
        manifest = {**record, **fingerprint, _HASH: digest}
        if jax.process_count() == 1:
            store._prepare(fingerprint, manifest, restart)
            return store
        if not restart:
            _check(folder / MANIFEST, fingerprint, digest)
        if jax.process_index() == 0:
            store._prepare(fingerprint, manifest, restart)
        process_barrier(f"{job}: folder prepared")
        return store

    def _prepare(self, fingerprint, manifest: dict[str, Any], restart: bool) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        if not restart and _check(self.folder / MANIFEST, fingerprint, self.digest):
            return
        for old in self.folder.glob("*.npz"):
            old.unlink()
        write_text_atomic(self.folder / MANIFEST, json.dumps(manifest, indent=2))

    def path(self, key: str) -> Path:
        """The file of the piece ``key``."""
        return self.folder / f"{key}.npz"

    def save(self, key: str, arrays: Mapping[str, Any]) -> None:
        """Write the piece ``key`` atomically (complete or absent)."""
        save_npz_atomic(self.path(key), **arrays)

    def done(self, keys: Iterable[str]) -> list[str]:
        """Those of ``keys`` whose file is there (read with :meth:`load` to know it whole)."""
        return [k for k in keys if self.path(k).exists()]

    def load(self, key: str, check: Callable[[Arrays], bool] | None = None) -> Arrays | None:
        """The arrays of the piece ``key``, or None where its file is absent, truncated,
        corrupt or fails ``check`` (then the piece is computed again)."""
        path = self.path(key)
        if not path.exists():
            return None
        try:
            with np.load(path) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception:  # truncated or corrupt: compute it again
            return None
        if check is not None and not check(arrays):
            return None
        return arrays

    def require(self, key: str, check: Callable[[Arrays], bool] | None = None) -> Arrays:
        """:meth:`load` after every process has written its pieces: a piece still missing
        or unreadable raises (the processes do not share one folder)."""
        arrays = self.load(key, check)
        if arrays is None:
            raise RuntimeError(
                f"{self.path(key)}: missing or unreadable after every process finished; "
                f"is {self.folder} one folder shared by all processes?"
            )
        return arrays
