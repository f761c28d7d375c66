"""A capture fit's tiles on disk: written as they finish, read back by a rerun or another process.

With an ``out_dir``, each finished tile is written to ``out_dir/tiles/tile_NNNNN.npz``
beside a ``manifest.json`` (both written atomically: a file there is complete or absent)
naming the job, the capture and the fit settings that ran
(:meth:`jaxrefl.svbrdf._tile_fitter.TileFitter.settings`). A rerun with the same job and
capture loads the tiles already there and computes only the missing ones (none is lost, none
recomputed); a different job or capture in the same folder is refused with a message, and a
corrupt tile file is recomputed. The settings that ran follow from the job and the capture
(the lean LM's compaction aside, which leaves per-pixel results as they are), so the check
compares those two.

Several processes share one folder (:class:`TileStore`): process 0 checks and prepares it
while the others wait; after every process has written its tiles, each reads the others'
(:meth:`TileStore.gather`).

:func:`fit_tiles` runs the tiles a process computes: a tile's data is read on a second thread
while the tile before it is fitted.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import process_barrier, process_gather
from jaxrefl.io import save_npz_atomic, write_text_atomic

from ._job_types import FitJob
from ._tile_fitter import STAGES, TileFitter

__all__ = ["TILE_KEYS", "TileStore", "fit_tiles", "manifest", "tile_ranges"]

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


def load_tile(path: Path, n: int) -> dict[str, np.ndarray] | None:
    """A saved tile of ``n`` pixels, or None where the file is truncated, corrupt, or holds
    another number of pixels or other arrays (then the tile is recomputed)."""
    try:
        with np.load(path) as z:
            tile = {k: z[k] for k in z.files}
    except Exception:  # truncated or corrupt: recompute it
        return None
    if any(k not in tile for k in TILE_KEYS) or any(
        v.ndim == 0 or v.shape[0] != n for v in tile.values()
    ):
        return None
    return tile


def _check_manifest(mpath: Path, new_manifest: dict[str, Any]) -> bool:
    """Whether ``mpath`` exists and names this job and capture (False: absent); raises where
    it is unreadable or names another fit (its tiles are not this fit's)."""
    if not mpath.exists():
        return False
    tiles = mpath.parent
    try:
        old = json.loads(mpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, OSError) as e:
        raise JaxreflError(
            f"{mpath}: unreadable resume manifest ({e}); the tiles beside it cannot be "
            "matched to this fit: use --restart (or another --out folder)"
        ) from None
    new = json.loads(json.dumps(new_manifest))  # as it reads back (tuples become lists)
    same = isinstance(old, dict) and all(old.get(k) == new[k] for k in _MATCHED)
    if not same:
        raise JaxreflError(
            f"{mpath}: the tiles in {tiles} belong to a different fit (another model, "
            "holdout, tile size, fit configuration or capture); use another --out "
            "folder or --restart"
        )
    return True


def _prepare_dir(out_dir: Path, new_manifest: dict[str, Any], restart: bool) -> Path:
    tiles = out_dir / "tiles"
    tiles.mkdir(parents=True, exist_ok=True)
    mpath = tiles / "manifest.json"
    if not restart and _check_manifest(mpath, new_manifest):
        return tiles
    for old_tile in tiles.glob("tile_*.npz"):
        old_tile.unlink()
    write_text_atomic(mpath, json.dumps(new_manifest, indent=2))
    return tiles


class TileStore:
    """The tile files of one fit in ``folder`` (``out_dir/tiles``), beside its manifest."""

    def __init__(self, folder: Path):
        self.folder = folder

    @classmethod
    def open(cls, out_dir: Path, new_manifest: dict[str, Any], restart: bool) -> TileStore:
        """The folder of ``out_dir`` prepared for this fit, in a job of one or more processes:
        every process checks the manifest (the same files give every process the same
        error), process 0 alone creates the folder, writes the manifest or clears old tiles,
        and the others wait for it. ``restart``: discard the tiles there."""
        if jax.process_count() == 1:
            return cls(_prepare_dir(out_dir, new_manifest, restart))
        if not restart:
            _check_manifest(out_dir / "tiles" / "manifest.json", new_manifest)
        if jax.process_index() == 0:
            _prepare_dir(out_dir, new_manifest, restart)
        process_barrier("jaxrefl fit: folder prepared")
        return cls(out_dir / "tiles")

    def path(self, i: int) -> Path:
        return self.folder / f"tile_{i:05d}.npz"

    def save(self, i: int, tile: dict[str, np.ndarray]) -> None:
        save_npz_atomic(self.path(i), **tile)

    def load_done(self, tiles: list[tuple[int, int]]) -> tuple[list[Any], int]:
        """(each tile's arrays where its file is there and readable, else None; how many)."""
        results: list[dict[str, np.ndarray] | None] = [None] * len(tiles)
        loaded = 0
        for i, (s, e) in enumerate(tiles):
            p = self.path(i)
            if p.exists():
                results[i] = load_tile(p, e - s)
                loaded += results[i] is not None
        return results, loaded

    def gather(
        self, tiles, results: list, computed: int, compile_s: float, run_s: float
    ) -> np.ndarray:
        """Wait for every process's tiles, read those of the others into ``results``; returns
        (processes, 3): tiles computed, compile seconds, run seconds of each process."""
        process_barrier("jaxrefl fit: tiles written")
        for i, r in enumerate(results):
            if r is None:
                s, e = tiles[i]
                results[i] = load_tile(self.path(i), e - s)
                if results[i] is None:
                    raise RuntimeError(
                        f"{self.path(i)}: missing or unreadable after every process "
                        "finished; is the output folder one shared folder for all processes?"
                    )
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

    def read(j: int):
        return fitter.data(*tiles[todo[j]])

    # The next tile's data is read on a second thread while this one is fitted (reading is
    # NumPy work on the host, the fit XLA's); ``read`` counts only the wait for it.
    with ThreadPoolExecutor(max_workers=1) as pool:
        ahead: Future | None = pool.submit(read, 0)
        for j, i in enumerate(iterator):
            s, e = tiles[i]
            t0 = time.perf_counter()
            assert ahead is not None
            data = ahead.result()
            ahead = pool.submit(read, j + 1) if j + 1 < len(todo) else None
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
