"""Regenerate the lobe figure, the directional-albedo figure and the stability table.

    python paper_figures/lobes_and_stability.py [--out paper_figures]

Writes ``lobes.png`` (polar slices of f_r·cos in the plane of incidence at 0/30/60/75
degrees), ``albedo.png`` + ``albedo.csv`` (directional albedo against outgoing angle) and
``stability.csv`` + ``stability.png`` (the edge-case sweep of ``benchmarks/stability.py``),
all from the public API.
"""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import asdict
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxrefl.plot import albedo_curve, plot_albedo, plot_lobes, showcase  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _stability_sweep import run_stability  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    models = showcase()
    plot_lobes(models).savefig(args.out / "lobes.png", dpi=120)
    plot_albedo(models).savefig(args.out / "albedo.png", dpi=120)
    with open(args.out / "albedo.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        th = None
        cols = {}
        for label, (m, p) in models.items():
            th, rho = albedo_curve(m, p)
            cols[label] = rho
        w.writerow(["theta_o_deg", *cols])
        for i, t in enumerate(th):
            w.writerow([f"{t:.3f}", *(f"{cols[k][i]:.6f}" for k in cols)])

    rows = run_stability()
    with open(args.out / "stability.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(asdict(rows[0])))
        w.writeheader()
        w.writerows(asdict(r) for r in rows)
    labels = sorted({r.label for r in rows}, key=[r.label for r in rows].index)
    fig, ax = plt.subplots(figsize=(8, 0.22 * len(labels) + 1.5))
    y = np.arange(len(labels))
    for off, dt in ((-0.2, "float32"), (0.2, "float64")):
        cases = [next(r.cases for r in rows if r.label == lb and r.dtype == dt) for lb in labels]
        bad = [
            next(
                r.nonfinite_values + r.nonfinite_grads
                for r in rows
                if r.label == lb and r.dtype == dt
            )
            for lb in labels
        ]
        ax.barh(y + off, cases, height=0.4, label=f"{dt}: cases (non-finite: {sum(bad)})")
    ax.set_yticks(y, labels, fontsize=6)
    ax.set_xlabel("edge cases checked (value + gradient wrt every parameter)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.out / "stability.png", dpi=120)
    total = sum(r.cases for r in rows)
    bad = sum(r.nonfinite_values + r.nonfinite_grads for r in rows)
    print(f"wrote figures to {args.out}; stability: {total} cases, {bad} non-finite")


if __name__ == "__main__":
    main()
