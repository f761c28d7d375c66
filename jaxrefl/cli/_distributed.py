"""The multi-process flags shared by ``jaxrefl fit`` and ``jaxrefl sample``.

``--distributed`` runs the command as one process of a group on JAX's distributed runtime
(:class:`jaxrefl.fit.Distributed`); ``--coordinator HOST:PORT``, ``--num-processes N`` and
``--process-id I`` name the group where the cluster's environment does not (JAX reads
SLURM's itself). Every process is started with the same command and ``--out``.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from jaxrefl._errors import JaxreflError

from ._main import positive_int

if TYPE_CHECKING:
    from jaxrefl.fit import Distributed

__all__ = ["add_distributed_arguments", "distributed_from_args"]


def _process_id(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"--process-id takes an integer >= 0, not {text!r}")
    return value


def add_distributed_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("several processes or hosts (JAX's distributed runtime)")
    g.add_argument(
        "--distributed",
        action="store_true",
        help="run as one process of a group sharing --out (same command in every process)",
    )
    g.add_argument("--coordinator", default=None, help="HOST:PORT of process 0 (default: env)")
    g.add_argument("--num-processes", type=positive_int, default=None, help="default: env")
    g.add_argument("--process-id", type=_process_id, default=None, help="default: env")


def distributed_from_args(args: argparse.Namespace) -> Distributed | None:
    """The :class:`~jaxrefl.fit.Distributed` of the flags, or None without --distributed."""
    named = [args.coordinator, args.num_processes, args.process_id]
    if not args.distributed:
        if any(v is not None for v in named):
            raise JaxreflError(
                "--coordinator, --num-processes and --process-id go with --distributed"
            )
        return None
    from jaxrefl.fit import Distributed

    return Distributed(
        coordinator=args.coordinator, num_processes=args.num_processes, process_id=args.process_id
    )
