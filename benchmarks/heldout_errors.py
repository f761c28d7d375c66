"""Where the held-out error of a real flash capture lies: new highlights and photo exposure.

For ``bath_tile`` and ``yellow_box`` (``../shared/data/svbrdf_flash``, read at ``--size``),
every photo is held out in turn and predicted by each model (``--models``, by default
``lambert`` and ``pooled``, the model ``auto`` chooses on both captures) fitted on the other
photos, as in ``benchmarks/real_captures.py``. The held-out photo's uncensored, valid
observations are then split in two:

* **new highlights**: pixels whose held-out value (mean over channels) is more than
  ``--novel`` (1.25) times the brightest value any training photo shows at that pixel
  (clipped training values count at their clip level: that photo saw the pixel at least
  that bright). No
  training photo saw such a pixel this bright, so no model fitted to them can know how
  bright it gets: a glint of a tile tilted towards this one camera position, or a
  highlight on a lobe whose peak fell between the training photos;
* the rest.

Printed per capture and model: the share of observations that are new highlights, the share
of the held-out squared error they carry, the held-out RMSE over all observations and over the
rest, and the ratio of each to Lambert's. Then the **exposure oracle**: the RMSE when each
held-out prediction is multiplied by the one scalar that best fits that held-out photo (least
squares over its observations). That scalar is fitted to the held-out photo itself, so this
figure is not a prediction; it measures how much of the error a per-photo exposure or flash
power difference (which the capture files do not record) accounts for.

    python benchmarks/heldout_errors.py [--size 256] [--captures bath_tile,yellow_box]
        [--models lambert,pooled] [--novel 1.25] [--no-write]

It prints the tables and writes them, dated and with the machine, to the section
``heldout_errors`` of ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _common import flash_capture, run_and_record, table  # noqa: E402


def anatomy(cap, model: str, novel_factor: float) -> dict[str, float]:
    """Sums over every held-out photo of one model's squared errors, split (module doc)."""
    from jaxrefl.io import ObsStatus
    from jaxrefl.svbrdf import FitJob, fit_capture, predict_photos

    k = cap.n_photos
    ok = cap.status == ObsStatus.OK  # uncensored, valid observations
    img = cap.images.astype(np.float64)
    # What a training photo saw: its valid values and its clipped ones (a clipped value is
    # a lower bound on the radiance, so a pixel clipped in training was seen that bright).
    seen = ok | (cap.status == ObsStatus.SATURATED)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # NaN where no channel qualifies
        lum = np.nanmean(np.where(ok, img, np.nan), axis=-1)  # (K, H, W)
        lum_seen = np.nanmean(np.where(seen, img, np.nan), axis=-1)
    acc = dict.fromkeys(("se", "n", "se_new", "n_new", "se_gain"), 0.0)
    t0 = time.perf_counter()
    for i in range(k):
        train = [j for j in range(k) if j != i]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a pixel valid in no training photo
            brightest = np.nanmax(lum_seen[train], axis=0)
        new = (lum[i] > novel_factor * np.nan_to_num(brightest, nan=np.inf))[..., None] & ok[i]
        fit = fit_capture(cap, FitJob(model=model, holdout=(i,)))
        _shot, pred = predict_photos(fit, cap, [i])
        p = pred[0]
        use = ok[i] & np.isfinite(p)
        e2 = np.where(use, (img[i] - np.nan_to_num(p)) ** 2, 0.0)
        pp = np.where(use, p, 0.0)
        g = float(np.sum(pp * np.where(use, img[i], 0.0)) / max(np.sum(pp * pp), 1e-300))
        acc["se"] += float(e2.sum())
        acc["n"] += float(use.sum())
        acc["se_new"] += float(e2[new & use].sum())
        acc["n_new"] += float((new & use).sum())
        acc["se_gain"] += float(np.sum(np.where(use, (img[i] - g * pp) ** 2, 0.0)))
    acc["seconds"] = time.perf_counter() - t0
    return acc


def run_capture(name: str, size: int, models: list[str], novel: float) -> None:
    cap = flash_capture(name, size)
    res = {m: anatomy(cap, m, novel) for m in models}
    lam = res.get("lambert")

    def rmse(a, which):
        if which == "all":
            return np.sqrt(a["se"] / a["n"])
        if which == "rest":
            return np.sqrt((a["se"] - a["se_new"]) / (a["n"] - a["n_new"]))
        return np.sqrt(a["se_gain"] / a["n"])

    rows = []
    for m, a in res.items():
        cells = [
            m,
            f"{100 * a['n_new'] / a['n']:.1f}",
            f"{100 * a['se_new'] / a['se']:.0f}",
        ]
        for which in ("all", "rest", "gain"):
            r = rmse(a, which)
            ratio = r / rmse(lam, which) if lam is not None else float("nan")
            cells += [f"{r:.4f}", f"{ratio:.2f}"]
        cells.append(f"{a['seconds']:.0f}")
        rows.append(cells)
    print(
        f"### {name}, {size} x {size}, {cap.n_photos} photos, each held out in turn "
        f"(new highlight: more than {novel:g} x the pixel's brightest training value)"
    )
    print()
    print(
        table(
            [
                "model",
                "new-highlight obs %",
                "their share of SE %",
                "RMSE all",
                "/ Lambert",
                "RMSE without new highlights",
                "/ Lambert",
                "RMSE, exposure oracle",
                "/ Lambert",
                "s (9 folds, compile incl.)",
            ],
            rows,
        )
    )
    print()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--captures", default="bath_tile,yellow_box")
    ap.add_argument("--models", default="lambert,pooled")
    ap.add_argument("--novel", type=float, default=1.25)
    args = ap.parse_args()
    models = [m for m in args.models.split(",") if m]
    print(
        "Held-out observations: uncensored and valid; raw (unclipped) predictions in linear "
        "radiance. SE: squared error summed over every held-out photo. The exposure oracle "
        "rescales each held-out prediction by a scalar fitted to that photo: not a prediction."
    )
    print()
    for name in [c for c in args.captures.split(",") if c]:
        run_capture(name, args.size, models, args.novel)
    return 0


if __name__ == "__main__":
    sys.exit(run_and_record("heldout_errors", "Where the held-out error lies", main))
