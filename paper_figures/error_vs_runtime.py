"""Fit error against run time, with the Pareto front of every material marked.

    python paper_figures/error_vs_runtime.py [--run] [--out paper_figures]

Reads ``error_vs_runtime.csv`` (written by ``benchmarks/error_vs_runtime.py --csv``; with
``--run`` the benchmark is run first, from the public API) and draws one panel per
material: the cosine-weighted L2 error (Ngan et al. 2005, 1/sr) against the warm wall time
of the fit (compile apart), one marker per model (colour), backend (shape) and dtype
(filled: float32, open: float64); the Pareto front (no other configuration is both
faster and more accurate) is joined by a line and its points ringed. Writes
``error_vs_runtime.png`` beside the CSV.
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import NullFormatter

HERE = Path(__file__).resolve().parent
MARKERS = {"lean": "o", "optimistix": "s", "jaxopt": "^"}


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        for k in ("cosine_weighted_l2", "log_l2", "relative_l2", "fit_time_s", "compile_time_s"):
            r[k] = float(r[k])
        r["pareto"] = r["pareto"] == "True"
        r["fit_time_s"] = float(r["fit_time_s"])
    return rows


def plot(rows: list[dict], out: Path) -> None:
    mats = list(dict.fromkeys(r["material"] for r in rows))
    models = list(dict.fromkeys(r["model"] for r in rows))
    colours = {m: plt.cm.tab10(i) for i, m in enumerate(models)}
    ncol = min(3, len(mats))
    nrow = -(-len(mats) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.4 * nrow), squeeze=False)
    for ax, mat in zip(axes.flat, mats, strict=False):
        rs = [r for r in rows if r["material"] == mat]
        for r in rs:
            c = colours[r["model"]]
            filled = r["dtype"] == "float32"
            ax.scatter(
                1e3 * r["fit_time_s"],
                r["cosine_weighted_l2"],
                marker=MARKERS.get(r["backend"], "x"),
                s=36,
                facecolors=c if filled else "none",
                edgecolors=c,
                linewidths=1.2,
            )
        front = sorted((r for r in rs if r["pareto"]), key=lambda r: r["fit_time_s"])
        if front:
            t = [1e3 * r["fit_time_s"] for r in front]
            e = [r["cosine_weighted_l2"] for r in front]
            ax.step(t, e, where="post", color="k", lw=1.0, alpha=0.7)
            ax.scatter(t, e, s=130, facecolors="none", edgecolors="k", linewidths=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_title(mat, fontsize=10)
        ax.set_xlabel("fit wall time [ms] (compile apart)")
        ax.set_ylabel("cosine-weighted L2 [1/sr]")
        ax.grid(True, which="both", alpha=0.2)
    for ax in list(axes.flat)[len(mats) :]:
        ax.axis("off")
    handles = [plt.Line2D([], [], ls="", marker="o", color=colours[m], label=m) for m in models] + [
        plt.Line2D([], [], ls="", marker=mk, color="grey", mfc="none", label=b)
        for b, mk in MARKERS.items()
    ]
    handles += [
        plt.Line2D([], [], ls="", marker="o", color="grey", label="float32 (filled)"),
        plt.Line2D([], [], ls="", marker="o", color="grey", mfc="none", label="float64 (open)"),
        plt.Line2D([], [], color="k", label="Pareto front"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=6, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(out, dpi=130)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=HERE)
    ap.add_argument("--run", action="store_true", help="run the benchmark first")
    args = ap.parse_args()
    csv_path = args.out / "error_vs_runtime.csv"
    if args.run:
        bench = HERE.parent / "benchmarks" / "error_vs_runtime.py"
        subprocess.run([sys.executable, str(bench), "--csv", str(csv_path)], check=True)
    rows = read_rows(csv_path)
    # The front by the benchmark's rule (errors within 0.1% count as equal), written back so
    # that the CSV beside the picture says what the picture shows.
    sys.path.insert(0, str(HERE.parent / "benchmarks"))
    from error_vs_runtime import mark_pareto

    mark_pareto(rows)
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, args.out / "error_vs_runtime.png")
    front = [r for r in rows if r["pareto"]]
    print(f"{len(rows)} fits, {len(front)} on a front; wrote {args.out / 'error_vs_runtime.png'}")
    for r in front:
        print(
            f"  {r['material']:22s} {r['model']:18s} {r['backend']:10s} {r['dtype']}  "
            f"{1e3 * r['fit_time_s']:8.1f} ms  {r['cosine_weighted_l2']:.4g}"
        )
    return 0 if np.isfinite([r["cosine_weighted_l2"] for r in front]).all() else 1


if __name__ == "__main__":
    sys.exit(main())
