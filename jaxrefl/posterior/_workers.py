"""Independent chunks of work run a few at a time in threads, their results in order.

A map's MCMC chunks are independent compiled programs. On a CPU, XLA runs one such
program on part of the cores only (its vectorised loops are mostly single-threaded), and
a chunk's summaries (R-hat, ESS: NumPy) leave the cores idle between programs. JAX
releases Python's global interpreter lock while a compiled program runs, so a second
thread can run the next chunk meanwhile: :func:`in_order` does that from the first item
on (threads that need the same program at once share one compilation: JAX's compilation
cache waits for the thread that is compiling it), with at most ``2 x workers`` results
waiting, so memory stays bounded however many chunks a map has. The results are those of
a loop: each item's work depends on the item only (its seed included), not on the thread
that ran it.

:func:`default_workers` is 2 on a CPU backend with at least two cores and 1 elsewhere:
an accelerator runs a chunk at full width by itself, and JAX already overlaps its host
work. On a CPU with more cores, more workers may pay; each holds one chunk's arrays
(``benchmarks/posterior_speed.py`` measures the map with the default).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

import jax

__all__ = ["default_workers", "in_order"]

T = TypeVar("T")
R = TypeVar("R")


def default_workers() -> int:
    """Chunks to run at once by default (module docstring)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return 2 if jax.default_backend() == "cpu" and cores >= 2 else 1


def in_order(fn: Callable[[T], R], items: Iterable[T], workers: int) -> Iterator[R]:
    """``fn(item)`` for each item, yielded in the items' order; with ``workers > 1`` the
    items run ``workers`` at a time in threads (module docstring). An exception in ``fn``
    is raised here, at its item; items not yet started are then cancelled."""
    it = iter(items)
    if workers <= 1:
        for item in it:
            yield fn(item)
        return
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="jaxrefl-chunk")
    waiting: deque[Future[R]] = deque()
    try:
        for item in it:
            waiting.append(pool.submit(fn, item))
            if len(waiting) >= 2 * workers:
                yield waiting.popleft().result()
        while waiting:
            yield waiting.popleft().result()
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
