"""Independent work on threads, its results in the items' order: written once for the package.

Three kinds of work run on threads while the calling thread goes on: a map's MCMC chunks
(:mod:`jaxrefl.posterior._chunks`), the model choice's candidates
(:mod:`jaxrefl.svbrdf._auto`) and the next tile's data, read while a tile is fitted
(:mod:`jaxrefl.svbrdf._tile_store`). JAX releases Python's global interpreter lock while a
compiled program runs and NumPy while it copies, so a second thread works meanwhile. Threads
that need the same program at once share one compilation: JAX's compilation cache waits for
the thread that is compiling it. The results are those of a loop: each item's work depends
on the item only (its seed included), not on the thread that ran it.

:func:`threaded` is the one pool: ``fn(item)`` on ``threads`` threads, yielded in the items'
order, with at most ``window`` items handed to the threads and not yet yielded, so memory
stays bounded however many items there are (a window of 2 on one thread reads one item
ahead; a window of at least the item count starts every item at once). An exception in
``fn`` is raised at its item; on leaving early (that exception, one in the caller, or the
caller closing the iterator) the items not yet started are cancelled, and those running
are waited for when ``wait`` is set (a candidate's or a read's few seconds) or left to
finish in the background when not (a chunk's minutes).

:func:`in_order` is the MCMC chunks' use of it: with ``workers`` at most 1 the items run in
the calling thread, otherwise on ``workers`` threads with ``2 x workers`` items in flight.
:func:`default_workers` is 2 on a CPU backend with at least two cores and 1 elsewhere: on a
CPU, XLA runs one such program on part of the cores only (its vectorised loops are mostly
single-threaded), and a chunk's summaries (R-hat, ESS: NumPy) leave the cores idle between
programs; an accelerator runs a chunk at full width by itself, and JAX already overlaps its
host work. On a CPU with more cores, more workers may pay; each holds one chunk's arrays
(``benchmarks/posterior_speed.py`` measures the map with the default).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Generator, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

import jax

__all__ = ["default_workers", "in_order", "threaded"]

T = TypeVar("T")
R = TypeVar("R")

#: The threads of :func:`in_order`'s pool are named ``jaxrefl-chunk_<k>``.
CHUNK_THREAD_NAME = "jaxrefl-chunk"


def default_workers() -> int:
    """Chunks to run at once by default (module docstring)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return 2 if jax.default_backend() == "cpu" and cores >= 2 else 1


def threaded(
    fn: Callable[[T], R],
    items: Iterable[T],
    threads: int,
    window: int,
    *,
    wait: bool = False,
    name: str = "",
) -> Generator[R, None, None]:
    """``fn(item)`` for each item on ``threads`` threads, yielded in the items' order, with at
    most ``window`` (>= 1) items submitted and not yet yielded; ``name`` prefixes the threads'
    names (empty: the standard library's ``ThreadPoolExecutor-<n>``). An exception in ``fn``
    is raised here, at its item; on leaving early the items not yet started are cancelled and,
    with ``wait``, those running are waited for (module docstring)."""
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix=name)
    waiting: deque[Future[R]] = deque()
    try:
        for item in items:
            waiting.append(pool.submit(fn, item))
            if len(waiting) >= window:
                yield waiting.popleft().result()
        while waiting:
            yield waiting.popleft().result()
    finally:
        pool.shutdown(wait=wait, cancel_futures=True)


def in_order(fn: Callable[[T], R], items: Iterable[T], workers: int) -> Iterator[R]:
    """``fn(item)`` for each item, yielded in the items' order; with ``workers > 1`` the
    items run ``workers`` at a time in threads (:func:`threaded`, ``2 x workers`` in flight).
    An exception in ``fn`` is raised here, at its item; items not yet started are then
    cancelled."""
    if workers <= 1:
        for item in items:
            yield fn(item)
        return
    yield from threaded(fn, items, workers, 2 * workers, name=CHUNK_THREAD_NAME)
