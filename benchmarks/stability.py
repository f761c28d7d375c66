"""Stability table: finite values and gradients of every model at the edges of its domain.

    python benchmarks/stability.py [--full] [--csv out.csv]

Prints, per model and dtype, how many (parameter set x direction pair) cases were run, how
many gave a non-finite value or gradient (must be 0), and the largest finite magnitudes.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from dataclasses import asdict
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, table  # noqa: E402

from jaxrefl.brdf import model_zoo  # noqa: E402
from jaxrefl.brdf._stability import run_stability  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--full", action="store_true", help="every Cook-Torrance combination")
    ap.add_argument("--csv", type=Path, help="also write the rows as CSV")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = run_stability(model_zoo(full=args.full))
    dt = time.perf_counter() - t0
    print(f"# Stability sweep\nmachine: {machine()}\n")
    print(
        table(
            ["model", "dtype", "cases", "non-finite f", "non-finite grad", "max |f|", "max |grad|"],
            [
                [
                    r.label,
                    r.dtype,
                    r.cases,
                    r.nonfinite_values,
                    r.nonfinite_grads,
                    f"{r.max_abs_value:.3g}",
                    f"{r.max_abs_grad:.3g}",
                ]
                for r in rows
            ],
        )
    )
    total = sum(r.cases for r in rows)
    bad = sum(r.nonfinite_values + r.nonfinite_grads for r in rows)
    print(f"\n{len(rows)} rows, {total} cases, {bad} non-finite")
    print(f"sweep took {dt:.1f} s (compile included)")
    if args.csv:
        with open(args.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(asdict(rows[0])))
            w.writeheader()
            w.writerows(asdict(r) for r in rows)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
