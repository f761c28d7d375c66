"""A pass of a map's MCMC in chunks: which pixels each chunk holds, where it runs, whether it
runs, and what is said meanwhile (:class:`Chunks`).

Chunk size: the MCMC pixels run in chunks of at most ``chunk`` pixels, of one balanced size
(:func:`chunk_size`; the last one padded by repeating pixels, whose results are dropped), so
the sampler compiles once for the whole map whatever the number of pixels, and memory stays
bounded.

Chunks at once: a process samples ``workers`` chunks at a time, each in its own thread
(:mod:`jaxrefl._threads`; they share the program's one compilation); chunk i is
seeded ``seed + i`` wherever it runs, so the map does not depend on ``workers``.

Chunks on disk and across processes: with a folder, each chunk's draws are written there as
it finishes (:mod:`._chunk_files`: a :class:`jaxrefl.fit.WorkStore` per pass), and a rerun
reads the chunks it finds rather than sampling them (resume). In a job of several
processes (:class:`jaxrefl.fit.Distributed`) chunk i is sampled by process i mod n, with
seed ``seed + i`` as in one process; after a barrier every process reads every chunk in
order, so the map does not depend on the number of processes.

Bounded time and progress: with a ``deadline`` (a :func:`time.perf_counter` value) a chunk
is not started where the last finished chunk's wall time would carry it past the deadline
(the first chunk runs unless the deadline has passed); the pass yields it as not sampled.
``log`` (a function of one line of text) hears the pass's start and end and, every
:data:`HEARTBEAT_S` seconds while it runs, the chunks done and an estimate of the time left.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._threads import in_order
from jaxrefl.fit import PixelData, process_barrier, process_share

from ._choice import sample_pixels
from ._chunk_files import fingerprint, load_chunk, open_pass, save_chunk
from ._diagnostics import ChunkSummary, summarise
from ._logpost import LogPosterior
from ._options import GibbsOptions, HMCOptions
from ._samples import Samples

__all__ = ["CHUNK_ROUND", "HEARTBEAT_S", "Chunks", "chunk_size"]

HEARTBEAT_S = 30.0  # seconds between the progress lines of a pass (module docstring)
CHUNK_ROUND = 2  # a pass's chunk count is a multiple of it (chunk_size)


@dataclass
class Chunks:
    """The chunked passes of one map (module docstring): its posterior, data and normals,
    the most pixels per chunk, chunks at once, folder, progress bar, time limit and log."""

    lp: LogPosterior
    data: PixelData
    normals: np.ndarray | None
    chunk: int
    workers: int
    folder: Path | None = None
    progress: bool = False
    deadline: float | None = None
    log: Callable[[str], None] | None = None

    def run(
        self,
        idx,
        starts,
        opts: HMCOptions,
        gibbs: GibbsOptions | None,
        seed: int,
        desc: str,
        tag: str,
        size=None,
    ):
        """Sample the pixels ``idx`` in chunks of one compiled size (module docstring).

        size: pixels per chunk (None: the fewest balanced chunks of at most ``chunk``).
        starts(rows) -> (theta0 (R, D) or (R, chains, D), theta_std (R, D)) for the map's
        pixels ``rows``. Yields (real pixels, their Samples or None where the time limit
        came first, run seconds, their :class:`ChunkSummary` or None) in chunk order. The
        summaries (R-hat, ESS, quantiles: NumPy) are computed in the thread that sampled
        or read the chunk, so that two chunks' summaries run on two cores while the caller
        stores the last ones.
        """
        if size is None:
            size = chunk_size(idx.size, self.chunk, opts.batch_size)
        firsts = list(range(0, idx.size, size))
        many = jax.process_count() > 1
        mine = set(process_share(list(range(len(firsts)))))
        # A chunk file belongs to these pixels, starts of this pass, sampler settings,
        # priors and parameter box only (the draws' theta is in the box's unconstrained
        # coordinates): its folder carries their fingerprint, so another run's chunks never
        # match.
        store = None
        if self.folder is not None:
            space = self.lp.space
            box = (self.lp.labels, tuple(space.lower.tolist()), tuple(space.upper.tolist()))
            fp = fingerprint(tag, idx, (opts, gibbs, self.lp.priors), seed, size, box)
            store = open_pass(self.folder, tag, fp)
        bar = None
        if self.progress and jax.process_index() == 0:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(firsts), desc=desc, unit="chunk")

        pace = _Pace(desc, len(firsts), int(idx.size), self.log, self.workers)

        def get(ci: int) -> tuple[Samples, float, ChunkSummary] | _Skipped | None:
            real = idx[firsts[ci] : firsts[ci] + size]
            got = None if store is None else load_chunk(store, ci, real.size, self.lp.labels)
            if got is None and ci in mine:
                if pace.too_late(self.deadline):
                    return _SKIPPED
                t0 = time.perf_counter()
                got = self._sample(real, size, starts, opts, gibbs, seed + ci)
                if store is not None:
                    save_chunk(store, ci, *got)
                pace.took(time.perf_counter() - t0)
            if got is None or many:  # another process's chunk: read after the barrier
                return None
            return (*got, summarise(got[0]))

        try:
            with pace:
                for ci, got in enumerate(in_order(get, range(len(firsts)), self.workers)):
                    pace.done(ci, got is _SKIPPED)
                    if bar is not None:
                        bar.update(1)
                    if not many:
                        real = idx[firsts[ci] : firsts[ci] + size]
                        if got is _SKIPPED:
                            yield real, None, 0.0, None
                            continue
                        assert isinstance(got, tuple)  # one process: every chunk is its own
                        yield real, *got
        finally:
            if bar is not None:
                bar.close()
        if many:
            process_barrier(f"jaxrefl mcmc: {tag} pass")
            assert store is not None  # adaptive_uncertainty requires a folder here
            for ci, a in enumerate(firsts):
                real = idx[a : a + size]
                read = load_chunk(store, ci, real.size, self.lp.labels, required=True)
                assert read is not None
                yield real, *read, summarise(read[0])

    def _sample(self, real, size, starts, opts: HMCOptions, gibbs: GibbsOptions | None, seed):
        """(Samples of the pixels ``real``, run seconds): one chunk, padded to ``size``."""
        # pad the last chunk by repeating its pixels: one compiled shape for the map
        rows = np.resize(real, size)
        sub = jax.tree.map(lambda v: v[rows], self.data)
        th0, sd = starts(rows)
        nrm = None if self.normals is None else jnp.asarray(np.asarray(self.normals)[rows])
        smp = sample_pixels(
            self.lp, sub, th0, theta_std=sd, normals=nrm, options=opts, gibbs=gibbs, seed=seed
        )
        return smp.take(real.size), smp.run_s


class _Skipped:
    """A chunk not started: the time limit came first."""


_SKIPPED = _Skipped()


class _Pace:
    """One pass's chunks done, their wall time, and its progress lines (module docstring):
    the pass's start and end, and every :data:`HEARTBEAT_S` seconds from a timer thread the
    chunks done and the time left, estimated from the last chunk's wall time (the first
    round's also compile)."""

    def __init__(self, desc: str, chunks: int, pixels: int, log, workers: int) -> None:
        self.desc, self.chunks, self.pixels, self.log = desc, chunks, pixels, log
        self.workers = max(1, workers)
        self.n_done = self.n_skipped = 0
        self.last_s: float | None = None  # wall time of the last chunk sampled
        self.t0 = time.perf_counter()
        self._stop = threading.Event()
        self._timer: threading.Thread | None = None

    def __enter__(self) -> _Pace:
        if self.log is not None:
            self.log(f"{self.desc}: {self.pixels} pixels in {self.chunks} chunks")
            self._timer = threading.Thread(target=self._beat, daemon=True)
            self._timer.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._timer is not None:
            self._timer.join()
        if self.log is not None and exc[0] is None:
            tail = f", {self.n_skipped} left by the time limit" if self.n_skipped else ""
            self.log(f"{self.desc}: done in {time.perf_counter() - self.t0:.1f} s{tail}")

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            assert self.log is not None
            self.log(self.line())

    def line(self) -> str:
        el = time.perf_counter() - self.t0
        left = self.chunks - self.n_done
        eta = ""
        if self.last_s is not None and self.n_done:
            eta = f", about {max(1, left / self.workers) * self.last_s:.0f} s left"
        return f"{self.desc}: {self.n_done}/{self.chunks} chunks done, {el:.0f} s{eta}"

    def too_late(self, deadline: float | None) -> bool:
        """Whether a chunk started now would end past ``deadline`` (the last chunk's wall
        time ahead; before any chunk has run, only a deadline already passed stops it)."""
        if deadline is None:
            return False
        ahead = 0.0 if self.last_s is None else self.last_s
        return time.perf_counter() + ahead > deadline

    def took(self, seconds: float) -> None:
        self.last_s = seconds

    def done(self, ci: int, skipped: bool) -> None:
        self.n_done += 1
        self.n_skipped += skipped


def chunk_size(n: int, chunk: int, batch: int) -> int:
    """The fewest chunks of at most ``chunk`` pixels, balanced: ceil(n / ceil(n / chunk)),
    rounded up to a multiple of the sampler's ``batch`` where that stays within ``chunk``
    (sample_pixels pads a chunk to whole batches). 3,078 pixels in chunks of at most 2048,
    batches of 128, run as 2 chunks of 1664, not 2 of 2048 with 1,018 of them padding.
    The count is rounded up to a multiple of :data:`CHUNK_ROUND`: two workers (a CPU's
    default) are never left with one chunk and a core idle (11 chunks leave the last round
    one, 12 smaller ones do not; a pass of one chunk's pixels runs as two at once), and
    the partition, so the map, does not depend on the number of workers."""
    k = -(-n // chunk)
    k = min(-(-k // CHUNK_ROUND) * CHUNK_ROUND, n)
    size = -(-n // k)
    if size <= batch:  # one batch: sample_pixels does not pad it
        return size
    whole = -(-size // batch) * batch
    return whole if whole <= chunk else size
