"""A capture fit's tiles on disk: written as they finish, read back by a rerun or another process.

With an ``out_dir``, each finished tile is written to ``out_dir/tiles/tile_NNNNN.npz``, a
:class:`jaxrefl.fit.WorkStore` whose fingerprint is the job and the capture, and whose
``manifest.json`` records beside them the fit settings that ran
(:meth:`jaxrefl.svbrdf._tile_fitter.TileFitter.settings`). A rerun with the same job and
capture loads the tiles already there and computes only the missing ones (none is lost, none
recomputed); a different job or capture in the same folder is refused with the store's
message, and a corrupt tile file is recomputed. The settings that ran follow from the job
(the lean LM's compaction included: ``FitJob.compact``, as decided for the capture) and the
capture, so the fingerprint holds those two. A tile folder written before its manifest carried
the fingerprint's hash is refused (``--restart`` discards it).

Several processes share one folder (:class:`TileStore`): process 0 checks and prepares it
while the others wait; after every process has written its tiles, each reads the others'
(:meth:`TileStore.gather`).

:func:`fit_tiles` runs the tiles a process computes: a tile's data is read on a second thread
while the tile before it is fitted.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from contextlib import closing
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxrefl._threads import threaded
from jaxrefl.fit import WorkStore, process_barrier, process_gather, refuse_other_work

from ._job_types import FitJob
from ._tile_fitter import STAGES, TileFitter

__all__ = [
    "TILE_KEYS",
    "TileStore",
    "fit_tiles",
    "manifest",
    "refuse_other_capture",
    "tile_ranges",
]

# The arrays of a tile file (:meth:`TileFitter.__call__`'s result).
TILE_KEYS = (
    "theta",
    "status",
    "cost",
    "iterations",
    "n_used",
    "std",
    "corr",
    "noise_var",
    "flag",
    "sse",
    "cnt",
    "width_v",
    "width_s",
)
# The manifest entries a resumed fit must match (module docstring).
_MATCHED = ("job", "capture")


def tile_ranges(h: int, w: int, size: int) -> list[tuple[int, int]]:
    """[start, stop) of each tile of ``size`` pixels (row-major; the last one shorter)."""
    n = h * w
    return [(s, min(s + size, n)) for s in range(0, n, size)]


def _capture_fingerprint(capture) -> dict[str, Any]:
    k, h, w, c = capture.shape
    digest = hashlib.sha1()
    digest.update(
        np.ascontiguousarray(capture.images[:, :: max(1, h // 16), :: max(1, w // 16)]).tobytes()
    )
    digest.update(np.ascontiguousarray(capture.status).tobytes()[:1_000_000])
    return {
        "shape": [k, h, w, c],
        "source": None if capture.source is None else str(capture.source),
        "digest": digest.hexdigest(),
    }


def refuse_other_capture(out_dir: str | Path, capture) -> None:
    """Refuse, before any fitting, an ``out_dir`` whose tiles belong to another capture (a
    crop, a downsampling or other photos): the light and model choice that come before the
    tiles take a minute on a large capture (:func:`jaxrefl.fit.refuse_other_work`)."""
    refuse_other_work(Path(out_dir) / "tiles", {"capture": _capture_fingerprint(capture)})


def manifest(job: FitJob, capture, n_tiles: int, ran: dict[str, Any]) -> dict[str, Any]:
    """The folder's ``manifest.json``: the job, the settings that ran (``ran``), the capture."""
    from jaxrefl import __version__

    return {
        "job": job.to_json(),
        "ran": ran,
        "capture": _capture_fingerprint(capture),
        "n_tiles": n_tiles,
        "jaxrefl": __version__,
    }


def _whole(n: int) -> Callable[[dict[str, np.ndarray]], bool]:
    """Whether a tile file's arrays are a tile of ``n`` pixels: every array of
    :data:`TILE_KEYS`, each of ``n`` rows (else the tile is recomputed)."""

    def check(tile: dict[str, np.ndarray]) -> bool:
        return all(k in tile for k in TILE_KEYS) and all(
            v.ndim > 0 and v.shape[0] == n for v in tile.values()
        )

    return check


class TileStore:
    """The tile files of one fit in ``out_dir/tiles`` (a :class:`jaxrefl.fit.WorkStore`),
    beside its manifest."""

    def __init__(self, work: WorkStore):
        self.work = work
        self.folder = work.folder

    @classmethod
    def open(cls, out_dir: Path, new_manifest: dict[str, Any], restart: bool) -> TileStore:
        """The folder ``out_dir/tiles`` prepared for this fit (:meth:`WorkStore.open`: every
        process checks the manifest, process 0 alone prepares the folder). The manifest's
        job and capture are the fingerprint; its other entries are recorded beside them.
        ``restart``: discard the tiles there."""
        fingerprint = {k: new_manifest[k] for k in _MATCHED}
        record = {k: v for k, v in new_manifest.items() if k not in _MATCHED}
        work = WorkStore.open(
            Path(out_dir) / "tiles", fingerprint, restart, record=record, job="jaxrefl fit"
        )
        return cls(work)

    @staticmethod
    def key(i: int) -> str:
        return f"tile_{i:05d}"

    def path(self, i: int) -> Path:
        return self.work.path(self.key(i))

    def save(self, i: int, tile: dict[str, np.ndarray]) -> None:
        self.work.save(self.key(i), tile)

    def load_done(self, tiles: list[tuple[int, int]]) -> tuple[list[Any], int]:
        """(each tile's arrays where its file is there and readable, else None; how many)."""
        results = [self.work.load(self.key(i), _whole(e - s)) for i, (s, e) in enumerate(tiles)]
        return results, sum(r is not None for r in results)

    def gather(
        self, tiles, results: list, computed: int, compile_s: float, run_s: float
    ) -> np.ndarray:
        """Wait for every process's tiles, read those of the others into ``results``; returns
        (processes, 3): tiles computed, compile seconds, run seconds of each process."""
        process_barrier("jaxrefl fit: tiles written")
        for i, r in enumerate(results):
            if r is None:
                s, e = tiles[i]
                results[i] = self.work.require(self.key(i), _whole(e - s))
        stats = np.array([computed, compile_s, run_s], np.float64)
        return process_gather(stats, "jaxrefl fit: timings gathered")


def fit_tiles(
    fitter: TileFitter,
    tiles: list[tuple[int, int]],
    todo: list[int],
    results: list,
    store: TileStore | None,
    *,
    on_tile: Callable[[int, int], None] | None = None,
    progress: bool = False,
) -> tuple[list[float], float]:
    """Fit the tiles ``todo`` (indices into ``tiles``) into ``results``, each saved to
    ``store`` as it finishes. Returns (each tile's seconds, from waiting for its data to
    writing its file; compile seconds: a warm-up call on the first tile's data minus the
    same tile's time in the run). The fitter's ``stage_s`` counts the tiles, not the warm-up.
    """
    compile_s = 0.0
    times: list[float] = []
    if not todo:
        return times, compile_s
    s0, e0 = tiles[todo[0]]
    t0 = time.perf_counter()
    jax.block_until_ready(fitter(fitter.data(s0, e0), e0 - s0))
    warm = time.perf_counter() - t0
    fitter.stage_s = dict.fromkeys(STAGES, 0.0)  # the warm-up call is not a tile
    iterator: Any = todo
    if progress and jax.process_index() == 0:
        from tqdm.auto import tqdm

        iterator = tqdm(todo, desc="fit tiles", unit="tile")

    def read(i: int):
        return fitter.data(*tiles[i])

    # The next tile's data is read on a second thread while this one is fitted (reading is
    # NumPy work on the host, the fit XLA's): one thread, one tile ahead (a window of two).
    # ``read`` counts only the wait for it.
    with closing(threaded(read, todo, 1, 2, wait=True)) as ahead:
        for i in iterator:
            s, e = tiles[i]
            t0 = time.perf_counter()
            data = next(ahead)
            fitter.stage_s["read"] += time.perf_counter() - t0
            out = fitter(data, e - s)
            t1 = time.perf_counter()
            if store is not None:
                store.save(i, out)
            t2 = time.perf_counter()
            fitter.stage_s["write"] += t2 - t1
            times.append(t2 - t0)
            results[i] = out
            if on_tile is not None:
                on_tile(i, len(tiles))
    return times, max(0.0, warm - times[0])
