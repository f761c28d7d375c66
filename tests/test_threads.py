"""The one thread pool for independent work (jaxrefl._threads): results in the items' order,
a bounded window of items in flight, errors at their item, and the threads' names."""

from __future__ import annotations

import threading

import pytest

from jaxrefl._threads import CHUNK_THREAD_NAME, in_order, threaded


def test_threaded_yields_in_the_items_order_whatever_finishes_first():
    gates = [threading.Event() for _ in range(4)]
    finished: list[int] = []

    def fn(i: int) -> int:
        # Item i finishes only after item i + 1 has: the threads finish in reverse order.
        if i + 1 < len(gates):
            gates[i + 1].wait(60.0)  # a bound, so that a pool without threads cannot hang
        finished.append(i)
        gates[i].set()
        return i * i

    assert list(threaded(fn, range(4), 4, 4)) == [0, 1, 4, 9]
    assert finished == [3, 2, 1, 0]


@pytest.mark.parametrize(("threads", "window"), [(1, 2), (2, 4), (3, 3)])
def test_threaded_keeps_at_most_window_items_submitted_and_not_yielded(threads, window):
    started: list[int] = []
    lock = threading.Lock()

    def fn(i: int) -> int:
        with lock:
            started.append(i)
        return i

    out = []
    for got in threaded(fn, range(10), threads, window):
        with lock:
            # Yielding item ``got``: it and at most window - 1 items after it were submitted.
            assert max(started) <= got + window - 1
        out.append(got)
    assert out == list(range(10))


def test_one_thread_with_a_window_of_two_reads_one_item_ahead():
    """The tile store's read-ahead: while the caller holds item j, item j + 1 is read."""
    done: list[int] = []
    read_one = threading.Event()

    def read(i: int) -> int:
        done.append(i)
        if i == 1:
            read_one.set()
        return i

    ahead = threaded(read, range(3), 1, 2, wait=True)
    assert next(ahead) == 0
    read_one.wait(60.0)  # item 1 runs on the thread without the caller asking for it
    assert done == [0, 1]
    assert list(ahead) == [1, 2]


def test_an_error_is_raised_at_its_item_and_later_items_are_not_started():
    started: list[int] = []

    def fn(i: int) -> int:
        started.append(i)
        if i == 2:
            raise ValueError("item 2")
        return i

    got = []
    with pytest.raises(ValueError, match="item 2"):
        for v in threaded(fn, range(50), 1, 3, wait=True):
            got.append(v)
    assert got == [0, 1]
    assert max(started) <= 2 + 3 - 1  # the window of three stopped the submissions


def test_wait_waits_for_running_items_when_the_caller_leaves_early():
    release = threading.Event()
    finished: list[int] = []

    def fn(i: int) -> int:
        if i == 1:
            release.wait(5.0)
        finished.append(i)
        return i

    it = threaded(fn, range(2), 2, 2, wait=True)
    assert next(it) == 0
    threading.Timer(0.05, release.set).start()
    it.close()  # waits for item 1, which the timer lets finish
    assert finished == [0, 1]


def test_thread_names():
    def name(_: int) -> str:
        return threading.current_thread().name

    assert all(n.startswith(CHUNK_THREAD_NAME) for n in in_order(name, range(4), 2))
    assert all(n.startswith("ThreadPoolExecutor-") for n in threaded(name, range(2), 2, 2))
    main = threading.current_thread().name
    assert list(in_order(name, range(2), 1)) == [main, main]  # one worker: no thread
