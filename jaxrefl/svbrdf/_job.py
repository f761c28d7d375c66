"""The main job: a planar capture in, per-pixel reflectance maps with uncertainty out.

:func:`fit_capture` fits every pixel of a :class:`jaxrefl.io.Capture` independently
(:func:`jaxrefl.fit.fit_pixels`, lean batched LM by default), computes the Laplace
covariance of every pixel (:func:`jaxrefl.fit.laplace`) and, for held-out photos, the
prediction error. Pixels go through in tiles of ``tile_pixels`` (row-major, the last one
padded), so the working set is one tile whatever the image size; every tile has the same
shape and reuses one compiled program.

The parts: the job's types (:mod:`._job_types`), the light (:mod:`._light`; checked by a
named model, :mod:`._light_check`) and the model (:mod:`._auto`) chosen first, then the
noise's shape (:mod:`._noise_level`), one tile fitted (:mod:`._tile_fitter`), the tiles
kept on disk for resume and shared between processes (:mod:`._tile_store`), and the tiles
turned into maps and a report (:mod:`._maps`).

Interruption and resume: with an ``out_dir``, each finished tile is written there; a rerun
with the same job and capture computes only the missing tiles, and a different job or capture
in the same folder is refused (:mod:`jaxrefl.svbrdf._tile_store`).

Several processes and hosts (``distributed``, a :class:`jaxrefl.fit.Distributed`): the
same job runs in every process on a shared ``out_dir``. Process 0 checks and prepares the
folder while the others wait; every process lists the missing tiles, then fits every n-th
of them from its id on (n processes) and writes them as above; after a barrier every
process reads the others' tiles and assembles the maps. Each tile is fitted by one process
with the one compiled tile program, so the maps equal a one-process run's bit for bit; a
process that dies leaves its finished tiles for a rerun (with any number of processes).
The report's ``timings.processes`` gives each process's tiles and seconds; ``run_s`` is
then the slowest process's.

Timings: ``compile_s`` is measured by a warm-up call on the first tile's data (time of that
call minus the time of the same tile in the run), ``run_s`` is the sum of the tiles' times
(from waiting for its data to writing its file). A tile's data is read on a second thread
while the tile before it is fitted.
``stages_s`` splits the tiles' time (warm-up excluded) into ``read`` (the wait for the
tile's :class:`~jaxrefl.fit.PixelData` from the photos), ``fit`` (:func:`~jaxrefl.fit.fit_pixels`:
start and solver), ``laplace``, ``errors`` (per-photo errors and the copy of the tile's
results to the host) and ``write`` (the tile file); each stage waits for its results, so
the split is exact up to the timer. ``choose_s`` is the time of ``auto``'s model choice.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import jax
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import Distributed, process_barrier, process_share

# FitJob, CaptureFit and map_name are imported from here by other modules of the package.
from jaxrefl.io import map_name

from ._auto import ModelChoice, choose_model
from ._job_types import CaptureFit, FitJob
from ._light import estimate_light
from ._light_check import check_light
from ._light_options import LightOptions
from ._maps import capture_maps, capture_report, distributed_timings, widen_shared
from ._noise_level import estimate_noise_level, with_noise
from ._tile_fitter import TileFitter
from ._tile_store import TileStore, fit_tiles, manifest, refuse_other_capture, tile_ranges

__all__ = ["CaptureFit", "FitJob", "fit_capture", "map_name"]


def fit_capture(
    capture,
    job: FitJob | None = None,
    out_dir: str | Path | None = None,
    *,
    restart: bool = False,
    progress: bool = False,
    on_tile: Callable[[int, int], None] | None = None,
    distributed: Distributed | None = None,
) -> CaptureFit:
    """Fit every pixel of ``capture`` (module docstring); returns the maps and a report.

    out_dir:  where tiles go (resume); None keeps everything in memory
    restart:  discard the tiles of an earlier run in ``out_dir``
    progress: show a tqdm progress bar over tiles
    on_tile:  called as ``on_tile(index, n_tiles)`` after each tile is saved (for tests
              and front ends; an exception raised there interrupts the run like Ctrl-C)
    distributed: run as one process of a group (:class:`jaxrefl.fit.Distributed`; every
              process calls ``fit_capture`` with the same capture, job and ``out_dir``, a
              folder they all see). Process 0 prepares ``out_dir``; the tiles missing
              there are split round-robin by process id, each written by its process
              alone; once all are in, every process returns the whole fit (process 0
              writes the outputs: :func:`write_outputs`). A process that dies leaves its
              finished tiles, which a rerun loads. Call ``distributed.initialize()``
              before loading the capture (:func:`jaxrefl.io.load_capture` computes with
              JAX, which fixes the process's devices); here it is a no-op then.

    The job's ``compact`` left None is decided by the capture's size
    (:meth:`FitJob.compacts`); the returned fit's job, its report and the resume manifest
    record the value that ran.
    """
    job = FitJob() if job is None else job
    if distributed is not None:
        if out_dir is None:
            raise JaxreflError(
                "a distributed fit needs out_dir: a folder every process can read and write "
                "(the processes exchange their tiles there)"
            )
        distributed.initialize()
    if out_dir is None and jax.process_count() > 1:
        raise JaxreflError(
            "fit_capture in a job of several processes needs out_dir: a folder every process "
            "can read and write (the processes exchange their tiles there)"
        )
    _k, h, w, c = capture.shape
    job = replace(job, compact=job.compacts(h * w))
    if out_dir is not None and not restart:
        refuse_other_capture(out_dir, capture)  # before the light and the model choice
    # The light first (the capture as the estimate places it): every model sees the same.
    t_light = time.perf_counter()
    light = estimate_light(capture, job.light, LightOptions.of_job(job))
    # A named model keeps auto's light only where it predicts held-out photos no worse.
    light = check_light(capture, light, job)
    capture = light.apply(capture)
    light_s = time.perf_counter() - t_light
    choice: ModelChoice | None = None
    t_choose = time.perf_counter()
    if job.model == "auto":
        choice = choose_model(capture, job)
        job = replace(job, model=choice.model)
    choose_s = time.perf_counter() - t_choose
    # The noise's shape with the model known (one tile of the model's, flat noise).
    t_noise = time.perf_counter()
    level = estimate_noise_level(capture, job)
    job = with_noise(job, level)
    noise_s = time.perf_counter() - t_noise
    fitter = TileFitter(capture, job, pooled=None if choice is None else choice.pooled)
    tiles = tile_ranges(h, w, job.tile_pixels)
    store = None
    results: list[dict[str, np.ndarray] | None] = [None] * len(tiles)
    loaded = 0
    if out_dir is not None:
        folder = manifest(job, capture, len(tiles), fitter.settings())
        store = TileStore.open(Path(out_dir), folder, restart)
        results, loaded = store.load_done(tiles)
    missing = [i for i, r in enumerate(results) if r is None]
    # Every process has listed the same missing tiles before any writes a new one.
    process_barrier("jaxrefl fit: tiles listed")
    todo = process_share(missing)
    times, compile_s = fit_tiles(
        fitter, tiles, todo, results, store, on_tile=on_tile, progress=progress
    )
    per_process = None
    if jax.process_count() > 1:
        assert store is not None  # fit_capture refuses several processes without out_dir
        per_process = store.gather(tiles, results, len(todo), compile_s, float(np.sum(times)))

    done = [r for r in results if r is not None]
    cat = {key: np.concatenate([r[key] for r in done]) for key in done[0]}
    width = widen_shared(fitter, cat)
    maps = capture_maps(fitter, cat, h, w, width)
    report = capture_report(fitter, cat, capture, job, maps, compile_s, times, len(tiles), loaded)
    if width is not None:
        report["pooled"]["width_laplace"] = width.as_dict()
    report["timings"]["stages_s"] = dict(fitter.stage_s)
    report["timings"]["choose_s"] = choose_s
    report["timings"]["light_s"] = light_s
    report["timings"]["noise_level_s"] = noise_s
    report["noise_level"] = level.as_dict()
    report["light"] = light.as_dict()
    if per_process is not None:
        distributed_timings(report, per_process, h * w * len(missing) / len(tiles))
    report["auto"] = None if choice is None else choice.as_dict()
    return CaptureFit(
        maps=maps,
        report=report,
        labels=fitter.space.labels,
        theta=cat["theta"],
        job=job,
        tiles_computed=len(todo),
        tiles_loaded=loaded,
        light=light,
        channels=c,
        alpha_min=fitter.alpha_min,
        pooled=fitter.pooled,
        noise_estimated=fitter.estimates_noise,
        sse=cat["sse"],
        cnt=cat["cnt"],
        auto=choice,
    )
