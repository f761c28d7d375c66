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
A process that stops sending heartbeats for ``heartbeat_timeout_s`` seconds makes the
coordination service stop the others: a dead process never leaves the rest waiting.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

import jax
import numpy as np

__all__ = ["Distributed", "process_barrier", "process_gather", "process_share"]

T = TypeVar("T")


@dataclass(frozen=True)
class Distributed:
    """The process group of a multi-process job (module docstring), immutable.

    coordinator:    ``host:port`` where process 0 serves JAX's coordination service
                    (reachable from every process); None: JAX's cluster detection
                    (e.g. SLURM's first node of the allocation)
    num_processes:  processes in the job (>= 1); None: from the environment
    process_id:     this process, 0 .. num_processes - 1; None: from the environment
    heartbeat_timeout_s: seconds without a heartbeat after which a process counts as
                    dead and the coordination service stops the others (JAX's default 100)
    """

    coordinator: str | None = None
    num_processes: int | None = None
    process_id: int | None = None
    heartbeat_timeout_s: int = 100

    def __post_init__(self) -> None:
        if self.coordinator is not None:
            host, sep, port = self.coordinator.rpartition(":")
            if not (sep and host and port.isdigit()):
                raise ValueError(
                    f"coordinator must be HOST:PORT (e.g. node01:12345), not {self.coordinator!r}"
                )
        if self.num_processes is not None and self.num_processes < 1:
            raise ValueError(f"num_processes must be >= 1, got {self.num_processes}")
        if self.process_id is not None and (
            self.process_id < 0
            or (self.num_processes is not None and self.process_id >= self.num_processes)
        ):
            raise ValueError(
                f"process_id must be in 0 .. num_processes - 1 ({self.num_processes}), "
                f"got {self.process_id}"
            )
        if self.heartbeat_timeout_s < 1:
            raise ValueError(f"heartbeat_timeout_s must be >= 1, got {self.heartbeat_timeout_s}")

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


def process_barrier(name: str) -> None:
    """Wait until every process has called ``barrier(name)`` (nothing with one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def process_gather(values: np.ndarray) -> np.ndarray:
    """(processes, ...) ``values`` (same shape and dtype everywhere) of every process, in
    process order; (1, ...) with one process."""
    values = np.asarray(values)
    if jax.process_count() == 1:
        return values[None]
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(values, tiled=False))
