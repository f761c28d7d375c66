"""One job over several processes and hosts, on JAX's own distributed runtime.

A :class:`Distributed` option names the process group: the coordinator's ``host:port``
(process 0's machine), the number of processes and this process's id. Fields left None
are read by :func:`jax.distributed.initialize` itself from the cluster's environment
(SLURM's ``SLURM_*`` variables, Open MPI, Kubernetes, Cloud TPU; JAX's cluster detection).
:meth:`Distributed.initialize` starts JAX's coordination service (process 0) or joins it
(the others); it must run before any JAX computation of the process.

Work is split without any protocol of its own: every process lists the same units of work
(tiles, MCMC chunks) in the same order, takes every ``n``-th one from its id on
(:func:`process_share`: round-robin, so that a region of slow pixels is spread over the
processes), and writes each result to a shared folder; :func:`process_barrier` (JAX's
:func:`~jax.experimental.multihost_utils.sync_global_devices`) waits for every process
before a step that reads what the others wrote. Small per-process figures (counts,
seconds) are exchanged with :func:`process_gather` (JAX's
:func:`~jax.experimental.multihost_utils.process_allgather`).

Cross-process collectives on CPU go through Gloo (``jax_cpu_collectives_implementation``,
JAX's default since 0.4.36; :meth:`Distributed.initialize` sets it where it is unset).

A process that dies (killed, out of memory) closes its connections, so the others fail at
their next barrier or gather at once: :func:`process_barrier` and :func:`process_gather`
raise :class:`ProcessGroupError`, naming the processes that had not reached that step (each
process first marks its arrival in the coordination service's key-value store, through
JAX's client handle ``jax._src.distributed.global_state.client``, which orbax uses too).
Everything written before is in the output folder, which a rerun resumes. End the process
with :func:`leave_group`: a normal interpreter exit runs JAX's shutdown barrier, which
waits for the dead process until ``heartbeat_timeout_s`` and then aborts with a C++ stack
trace. Where process 0 dies, its coordination service goes with it, and JAX ends the
others at once itself (status 134, with its own log). A process that stops sending
heartbeats for ``heartbeat_timeout_s`` seconds (a host lost from the network) makes the
coordination service stop the others, so no process is left waiting for ever.
"""

from __future__ import annotations

import itertools
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NoReturn, TypeVar

import jax
import numpy as np

from jaxrefl._errors import JaxreflError

__all__ = [
    "Distributed",
    "ProcessGroupError",
    "leave_group",
    "process_barrier",
    "process_gather",
    "process_share",
]

T = TypeVar("T")

# Cross-process steps in call order; every process calls them in the same order, so the
# n-th step has the same number everywhere (the key of the arrivals in the key-value store).
_STEPS = itertools.count()


class ProcessGroupError(RuntimeError):
    """A barrier or gather failed because a process of the group stopped (died, killed).

    step:      the barrier's name
    missing:   ids of the processes that had not reached ``step`` (one of them died);
               None where the coordination service was unreachable (process 0 died)
    processes: the number of processes in the group
    """

    def __init__(self, step: str, missing: list[int] | None, processes: int):
        self.step, self.missing, self.processes = step, missing, processes
        if missing is None:
            who = "process 0 (the coordinator) or another process"
        else:
            s = "es" if len(missing) > 1 else ""
            who = f"process{s} " + ", ".join(str(i) for i in missing)
        super().__init__(f"{who} of {processes} stopped (died or was killed) before {step!r}")


@dataclass(frozen=True)
class Distributed:
    """The process group of a multi-process job (module docstring), immutable.

    coordinator:    ``host:port`` where process 0 serves JAX's coordination service
                    (reachable from every process); None: JAX's cluster detection
                    (e.g. SLURM's first node of the allocation)
    num_processes:  processes in the job (>= 1); None: from the environment
    process_id:     this process, 0 .. num_processes - 1; None: from the environment
    heartbeat_timeout_s: seconds without a heartbeat after which a process counts as
                    dead and the coordination service stops the others (JAX's default
                    100); a process that dies outright is noticed sooner, at the others'
                    next barrier (:class:`ProcessGroupError`)
    """

    coordinator: str | None = None
    num_processes: int | None = None
    process_id: int | None = None
    heartbeat_timeout_s: int = 100

    def __post_init__(self) -> None:
        if self.coordinator is not None:
            host, sep, port = self.coordinator.rpartition(":")
            if not (sep and host and port.isdigit()):
                raise JaxreflError(
                    f"coordinator must be HOST:PORT (e.g. node01:12345), not {self.coordinator!r}"
                )
        if self.num_processes is not None and self.num_processes < 1:
            raise JaxreflError(f"num_processes must be >= 1, got {self.num_processes}")
        if self.process_id is not None and (
            self.process_id < 0
            or (self.num_processes is not None and self.process_id >= self.num_processes)
        ):
            raise JaxreflError(
                f"process_id must be in 0 .. num_processes - 1 ({self.num_processes}), "
                f"got {self.process_id}"
            )
        if self.heartbeat_timeout_s < 1:
            raise JaxreflError(f"heartbeat_timeout_s must be >= 1, got {self.heartbeat_timeout_s}")

    @property
    def is_main(self) -> bool:
        """Whether this is process 0, the one that writes a job's outputs (after
        :meth:`initialize`)."""
        return jax.process_index() == 0

    def initialize(self) -> None:
        """Start or join the process group (once per process; a second call does nothing).

        Must come before any JAX computation in the process: JAX fixes its devices when the
        first one runs."""
        if jax.distributed.is_initialized():
            return
        if getattr(jax.config, "jax_cpu_collectives_implementation", None) in (None, "", "none"):
            # CPU processes exchange nothing without it (the barrier is a collective).
            jax.config.update("jax_cpu_collectives_implementation", "gloo")
        try:
            jax.distributed.initialize(
                coordinator_address=self.coordinator,
                num_processes=self.num_processes,
                process_id=self.process_id,
                heartbeat_timeout_seconds=self.heartbeat_timeout_s,
            )
        except RuntimeError as e:
            raise RuntimeError(
                f"jax.distributed.initialize failed ({e}); initialise the process group "
                "before any JAX computation, and give --coordinator, --num-processes and "
                "--process-id where the cluster does not set them"
            ) from None


def process_share(items: list[T]) -> list[T]:
    """This process's share of ``items``: every n-th from its id on (n processes)."""
    return items[jax.process_index() :: jax.process_count()]


def _client() -> Any:
    """The coordination service's client of this process (its key-value store), or None."""
    from jax._src import distributed  # no public handle (module docstring)

    return distributed.global_state.client


def _step(name: str, collective: Callable[[], T]) -> T:
    """Run a cross-process ``collective`` named ``name``; :class:`ProcessGroupError` where
    it fails while a process had not arrived (module docstring)."""
    key = f"jaxrefl/arrived/{next(_STEPS)}/"
    client, me, n = _client(), jax.process_index(), jax.process_count()
    try:
        client.key_value_set(f"{key}{me}", "1")
    except Exception:  # marking is for the message only; the collective decides
        pass
    try:
        return collective()
    except Exception as e:  # Gloo reports a lost peer as a ValueError (XlaRuntimeError)
        try:
            arrived = {int(k.rsplit("/", 1)[1]) for k, _ in client.key_value_dir_get(key)}
            missing: list[int] | None = [i for i in range(n) if i not in arrived | {me}]
        except Exception:  # the service is process 0's: unreachable when it died
            missing = None
        if missing == []:
            raise  # every process arrived: not a stopped process
        raise ProcessGroupError(name, missing, n) from e


def process_barrier(name: str) -> None:
    """Wait until every process has called ``barrier(name)`` (nothing with one process).

    Raises :class:`ProcessGroupError` where a process stopped before reaching it."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        _step(name, lambda: multihost_utils.sync_global_devices(name))


def process_gather(values: np.ndarray, name: str = "gather") -> np.ndarray:
    """(processes, ...) ``values`` (same shape and dtype everywhere) of every process, in
    process order; (1, ...) with one process. Raises :class:`ProcessGroupError` where a
    process stopped before reaching it (``name`` names the step in that message)."""
    values = np.asarray(values)
    if jax.process_count() == 1:
        return values[None]
    from jax.experimental import multihost_utils

    return np.asarray(_step(name, lambda: multihost_utils.process_allgather(values, tiled=False)))


def leave_group(status: int) -> NoReturn:
    """End this process at once with exit ``status`` after a :class:`ProcessGroupError`.

    Flushes stdout and stderr and exits without Python's clean-up: that clean-up runs JAX's
    shutdown barrier, which would wait for the stopped process until the heartbeat timeout
    and then abort. Files already written (tiles, chunks) are complete: they are written
    atomically."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
