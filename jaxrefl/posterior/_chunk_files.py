"""A map's MCMC chunks on disk: one :class:`jaxrefl.fit.WorkStore` per pass, in a folder
named by the pass and the hash of its fingerprint (its pixels, sampler settings, seed, chunk
size and parameter box), one ``chunk_NNNNN.npz`` per chunk, written atomically (complete
or absent). Another run's pass has another fingerprint, so another folder: its chunks are
never read for this one. A file that is absent, truncated, corrupt or of another size reads
as None, and its chunk is sampled again. Chunk files written before the passes had folders
of their own (``<pass>_<hash>_NNNNN.npz`` beside them) are not read: those chunks are
sampled again.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from jaxrefl.fit import WorkStore, fingerprint_hash

from ._samples import Samples

__all__ = ["fingerprint", "load_chunk", "open_pass", "save_chunk"]


def fingerprint(tag, idx, settings, seed: int, size: int, box) -> dict[str, Any]:
    """The JSON-able fingerprint of one pass's chunks (module docstring)."""
    pixels = hashlib.sha1(np.ascontiguousarray(idx, np.int64).tobytes()).hexdigest()
    return {
        "pass": str(tag),
        "pixels": pixels,
        "settings": repr(settings),
        "seed": int(seed),
        "size": int(size),
        "box": repr(box),
    }


def open_pass(folder: Path, tag: str, fp: dict[str, Any]) -> WorkStore:
    """The store of one pass's chunks: ``folder/<tag>_<12 hex digits of the hash>``."""
    return WorkStore.open(
        folder / f"{tag}_{fingerprint_hash(fp)[:12]}", fp, job=f"jaxrefl mcmc: {tag}"
    )


def _key(ci: int) -> str:
    return f"chunk_{ci:05d}"


def save_chunk(store: WorkStore, ci: int, cut: Samples, run_s: float) -> None:
    """Chunk ``ci``'s draws, written atomically (complete or absent)."""
    arrays: dict[str, Any] = {"theta": cut.theta, "natural": cut.natural, "run_s": run_s}
    arrays.update({f"stats.{k}": v for k, v in cut.stats.items()})
    arrays.update({f"tuning.{k}": v for k, v in cut.tuning.items()})
    arrays["no_estimate"] = cut.no_estimate
    arrays["method"] = np.str_(cut.method)
    arrays["reparam"] = np.str_(cut.reparam)
    store.save(_key(ci), arrays)


def load_chunk(
    store: WorkStore, ci: int, m: int, labels, *, required: bool = False
) -> tuple[Samples, float] | None:
    """Chunk ``ci`` as written by :func:`save_chunk` for ``m`` pixels, or None where the file
    is absent, truncated, corrupt or of another size (then it is sampled again).
    ``required``: raise instead (:meth:`WorkStore.require`: after every process wrote)."""

    def check(a: dict[str, np.ndarray]) -> bool:
        return "theta" in a and a["theta"].ndim > 0 and a["theta"].shape[0] == m

    a = store.require(_key(ci), check) if required else store.load(_key(ci), check)
    if a is None:
        return None
    smp = Samples(
        theta=a["theta"],
        natural=a["natural"],
        labels=tuple(labels),
        stats={k[6:]: v for k, v in a.items() if k.startswith("stats.")},
        method=str(a["method"]),
        tuning={k[7:]: v for k, v in a.items() if k.startswith("tuning.")},
        run_s=float(a["run_s"]),
        no_estimate=a["no_estimate"],
        reparam=str(a["reparam"]),
    )
    return smp, float(a["run_s"])
