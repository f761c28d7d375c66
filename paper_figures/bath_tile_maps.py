"""The bath_tile reflectance maps with their uncertainty, and the held-out check.

    python paper_figures/bath_tile_maps.py [--downsample 4] [--data DIR] [--out paper_figures]

Fits the real phone-flash capture ``svbrdf_flash/bath_tile`` (MaterialGAN example data, Guo
et al. 2020; found in ``--data``, else ``$JAXREFL_SHARED_DATA``, else ``../shared/data``
beside the checkout), box-filtered by ``--downsample`` (default 4: 256 x 256), with the
``ggx`` model and the ``lambert`` baseline, both holding out photo 4. Writes

* ``bath_tile_maps.png``: the GGX diffuse albedo, specular F0, roughness = sqrt(alpha) and
  Laplace-flag map; the Laplace standard deviations of the three and the Lambertian albedo;
  held-out photo 4 against the GGX and Lambert predictions and the held-out RMSE per photo;
* ``bath_tile_maps.csv``: one row per model: held-out RMSE (overall and per photo, linear
  radiance over the uncensored observations) and median |error|, train RMSE, fit-status and
  Laplace-flag counts, the reliable-pixel fraction (flag 0), the median std of every
  parameter (over all pixels with a finite std, and over the reliable ones), and the
  compile/run timings of the tiled fit.

All from the public API (``jaxrefl.io.load_capture``, ``jaxrefl.svbrdf``, ``jaxrefl.fit``).
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import BoundaryNorm, ListedColormap, LogNorm

from jaxrefl import fit, svbrdf
from jaxrefl.io import load_capture

HOLDOUT = (4,)
MODELS = ("ggx", "lambert")
STD_MAPS = {  # parameter -> its std map
    "albedo.R": "albedo_std.R",
    "albedo.G": "albedo_std.G",
    "albedo.B": "albedo_std.B",
    "specular": "specular_std",
    "alpha": "alpha_std",
    "roughness": "roughness_std",
}
FLAG_COLORS = ["#2ca02c", "#1f1f1f", "#9467bd", "#1f77b4", "#ff7f0e", "#d62728"]


def default_data() -> Path:
    env = os.environ.get("JAXREFL_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def encode(x: np.ndarray) -> np.ndarray:
    """Linear radiance (or albedo) for display, with the capture's gamma 2.2."""
    return np.clip(np.nan_to_num(x, nan=0.0), 0.0, 1.0) ** (1 / 2.2)


def rgb(res, base: str = "albedo") -> np.ndarray:
    return np.stack([res.maps[f"{base}.{c}"] for c in "RGB"], axis=-1)


def flag_image(flag: np.ndarray) -> np.ndarray:
    """0 where reliable, else the index (1..) of the highest set :class:`fit.LaplaceFlag` bit."""
    out = np.zeros(flag.shape, int)
    for i, b in enumerate(fit.LaplaceFlag, start=1):
        out[(flag & int(b)) != 0] = i
    return out


def fmt(v) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return ""
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def csv_row(name: str, res, shot, pred, ok, factor: int) -> dict[str, object]:
    rep = res.report
    h, w = res.maps["status"].shape
    row: dict[str, object] = {
        "model": name,
        "downsample": factor,
        "height": h,
        "width": w,
        "holdout": " ".join(str(i) for i in rep["holdout"]),
        "heldout_rmse": rep["heldout_rmse"],
    }
    for k, v in rep["heldout_rmse_per_photo"].items():
        row[f"heldout_rmse_photo{k}"] = v
    row["heldout_median_abs_err"] = float(np.median(np.abs(pred - shot)[ok]))
    row["heldout_observations"] = rep["heldout_observations"]
    row["train_rmse"] = rep["train_rmse"]
    for k, v in rep["status_counts"].items():
        row[f"status_{k}"] = v
    for k, v in rep["laplace_flag_counts"].items():
        row[f"flag_{k}"] = v
    reliable = res.maps["laplace_flag"] == 0
    row["reliable_fraction"] = float(np.mean(reliable))
    for par, std_name in STD_MAPS.items():
        std = res.maps.get(std_name)
        row[f"median_std_{par}"] = None if std is None else float(np.nanmedian(std))
        good = None if std is None else std[reliable & np.isfinite(std)]
        row[f"median_std_reliable_{par}"] = (
            None if good is None or good.size == 0 else float(np.median(good))
        )
    tm = rep["timings"]
    row["compile_s"] = tm["compile_s"]
    row["run_s"] = tm["run_s"]
    row["pixels_per_s"] = tm["pixels_per_s"]
    return row


def figure(results, shot, pred, rows, factor: int):
    ggx, lam = results["ggx"], results["lambert"]
    fig, axes = plt.subplots(3, 4, figsize=(16, 12.4), layout="constrained")

    def show(ax, img, title, **kw):
        im = ax.imshow(img, **kw)
        ax.set_title(title, fontsize=10)
        ax.axis("off")
        if "cmap" in kw:
            fig.colorbar(im, ax=ax, fraction=0.046)

    def show_std(ax, img, title):
        good = img[np.isfinite(img) & (img > 0)]
        lo, hi = np.percentile(good, [1, 99])
        show(ax, img, title + " (log)", cmap="magma", norm=LogNorm(vmin=lo, vmax=hi))

    show(axes[0, 0], encode(rgb(ggx)), "GGX diffuse albedo (gamma 2.2)")
    show(axes[0, 1], ggx.maps["specular"], "GGX specular F0", cmap="viridis")
    show(axes[0, 2], ggx.maps["roughness"], "GGX roughness = sqrt(alpha)", cmap="viridis")
    flag = ggx.maps["laplace_flag"]
    norm = BoundaryNorm(np.arange(len(FLAG_COLORS) + 1) - 0.5, len(FLAG_COLORS))
    axes[0, 3].imshow(flag_image(flag), cmap=ListedColormap(FLAG_COLORS), norm=norm)
    axes[0, 3].set_title(
        f"GGX Laplace flag ({100 * np.mean(flag == 0):.1f}% reliable)", fontsize=10
    )
    axes[0, 3].axis("off")
    names = ["reliable"] + [b.name or "" for b in fit.LaplaceFlag]
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in FLAG_COLORS]
    axes[0, 3].legend(
        handles, names, fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, 0.0)
    )

    show_std(axes[1, 0], ggx.maps["albedo_std.G"], "std albedo (G)")
    show_std(axes[1, 1], ggx.maps["specular_std"], "std specular F0")
    show_std(axes[1, 2], ggx.maps["roughness_std"], "std roughness")
    show(axes[1, 3], encode(rgb(lam)), "Lambert albedo (gamma 2.2)")

    k0 = HOLDOUT[0]
    show(axes[2, 0], encode(shot[0]), f"photo {k0} (held out)")
    show(axes[2, 1], encode(pred["ggx"][0]), f"GGX prediction, photo {k0}")
    show(axes[2, 2], encode(pred["lambert"][0]), f"Lambert prediction, photo {k0}")
    ax = axes[2, 3]
    x = np.arange(len(HOLDOUT) + 1)
    for j, row in enumerate(rows):
        vals = [row["heldout_rmse"]] + [row[f"heldout_rmse_photo{k}"] for k in HOLDOUT]
        ax.bar(x + (j - 0.5) * 0.38, vals, width=0.38, label=row["model"])
        for xi, v in zip(x, vals, strict=True):
            ax.text(xi + (j - 0.5) * 0.38, v, f"{v:.3g}", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(x, ["all held out"] + [f"photo {k}" for k in HOLDOUT])
    tops = [row["heldout_rmse"] for row in rows]
    if max(tops) > 20 * min(tops):
        ax.set_yscale("log")
    ax.set_ylabel("held-out RMSE (linear radiance)")
    ax.set_title("prediction error of unseen photos", fontsize=10)
    ax.legend(fontsize=8)
    h, w = ggx.maps["status"].shape
    fig.suptitle(
        f"bath_tile (MaterialGAN data, Guo et al. 2020), {h}x{w} (downsample {factor}), "
        f"photo{'s' if len(HOLDOUT) > 1 else ''} {', '.join(map(str, HOLDOUT))} held out",
        fontsize=12,
    )
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--downsample", type=int, default=4, help="box-filter factor (default 4)")
    ap.add_argument("--data", type=Path, default=None, help="the shared/data folder")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    data = args.data if args.data is not None else default_data()
    cap = load_capture(data / "svbrdf_flash" / "bath_tile").downsample(args.downsample)
    print(cap)
    results, pred, rows = {}, {}, []
    shot = ok = None
    for name in MODELS:
        t0 = time.perf_counter()
        res = svbrdf.fit_capture(cap, svbrdf.FitJob(model=name, holdout=HOLDOUT))
        results[name] = res
        shot, pred[name] = svbrdf.predict_photos(res, cap, list(HOLDOUT))
        ok = cap.status[list(HOLDOUT)] == 0
        rows.append(csv_row(name, res, shot, pred[name], ok, args.downsample))
        print(
            f"{name}: {time.perf_counter() - t0:.1f} s, held-out RMSE "
            f"{res.report['heldout_rmse']:.4g}, train RMSE {res.report['train_rmse']:.4g}"
        )

    fields = list(dict.fromkeys(k for row in rows for k in row))
    with open(args.out / "bath_tile_maps.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        w.writerows({k: fmt(row.get(k)) for k in fields} for row in rows)
    fig = figure(results, shot, pred, rows, args.downsample)
    fig.savefig(args.out / "bath_tile_maps.png", dpi=80)
    print(f"wrote bath_tile_maps.png/.csv to {args.out} in {time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    main()
