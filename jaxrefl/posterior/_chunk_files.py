"""A map's MCMC chunks on disk: one ``.npz`` per chunk, named by the pass, a fingerprint of
its pixels, sampler settings, seed and parameter box, and the chunk's index, written
atomically (complete or absent). A file that is absent, truncated, corrupt or of another
size reads as None, and its chunk is sampled again.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from ._samples import Samples

__all__ = ["fingerprint", "load_chunk", "save_chunk"]


def fingerprint(tag, idx, settings, seed: int, size: int, box) -> str:
    """12 hex digits naming one pass's chunks (module docstring)."""
    h = hashlib.sha1(f"{tag} {settings!r} {seed} {size} {box}".encode())
    h.update(np.ascontiguousarray(idx, np.int64).tobytes())
    return h.hexdigest()[:12]


def save_chunk(path: Path, cut: Samples, run_s: float) -> None:
    """One chunk's draws, written to a temporary file then renamed (complete or absent)."""
    arrays: dict[str, Any] = {"theta": cut.theta, "natural": cut.natural, "run_s": run_s}
    arrays.update({f"stats.{k}": v for k, v in cut.stats.items()})
    arrays.update({f"tuning.{k}": v for k, v in cut.tuning.items()})
    arrays["no_estimate"] = cut.extra["no_estimate"]
    arrays["method"] = np.str_(cut.method)
    arrays["reparam"] = np.str_(cut.extra.get("reparam", "none"))
    from jaxrefl.io import save_npz_atomic

    save_npz_atomic(path, **arrays)


def load_chunk(path: Path, m: int, labels) -> tuple[Samples, float] | None:
    """A chunk written by :func:`save_chunk` for ``m`` pixels, or None where the file is
    absent, truncated, corrupt or of another size (then it is sampled again)."""
    if not path.exists():
        return None
    try:
        with np.load(path) as z:
            a = {k: z[k] for k in z.files}
    except Exception:  # truncated or corrupt: sample it again
        return None
    if a.get("theta") is None or a["theta"].shape[0] != m:
        return None
    smp = Samples(
        theta=a["theta"],
        natural=a["natural"],
        labels=tuple(labels),
        stats={k[6:]: v for k, v in a.items() if k.startswith("stats.")},
        method=str(a["method"]),
        tuning={k[7:]: v for k, v in a.items() if k.startswith("tuning.")},
        run_s=float(a["run_s"]),
        extra={"no_estimate": a["no_estimate"], "reparam": str(a["reparam"])},
    )
    return smp, float(a["run_s"])
