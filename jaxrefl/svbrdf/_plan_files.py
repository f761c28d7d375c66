"""Files of capture planning: a fit's folder read back, and a plan's ``plan.json`` and figures.

:func:`read_fit` turns the output folder of ``jaxrefl fit`` (``maps.exr`` and
``report.json``, :func:`jaxrefl.svbrdf.write_outputs`) back into a
:class:`~jaxrefl.svbrdf.CaptureFit` and the capture it was fitted to: theta from the
parameter maps, the job (model, held-out photos, noise model, loss, dtype) and ``pooled``'s
choice from the report, and the capture from the path, photo subset, resolution and
downsampling the report's ``capture`` records.

:func:`write_plan` writes

* ``plan.json``: ``ranking``, one entry per candidate, best first (:meth:`Plan.ranking`:
  ``photo`` for the photos of a capture, ``position`` the camera position (capture units,
  the sample frame: origin its centre, +z its normal), ``light_position``, ``gain`` (the
  criterion's), ``variance_reduction`` (a share), ``log_variance_reduction`` (mean log
  ratio), ``information`` (nats), ``gain_pixels``, ``gain_shared``, ``share_informed``,
  ``highlight`` and ``highlight_on_sample``), with ``criterion``, ``criterion_meaning``,
  ``light``, ``candidates`` (their kind), ``pixels``, ``pixels_sampled``, ``shared``,
  ``informed_gain``, ``units``, ``fit`` and ``capture``;
* ``highlights.png``: the sample (the mean of the fitted photos) with where the highlight
  of each of the best ``top`` candidates would fall (a circle of the lobe's half-peak
  radius, numbered by rank);
* ``positions.png``: a top-down diagram of the candidate camera positions coloured by gain,
  the fitted photos' cameras and the sample's outline.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from jaxrefl import fit
from jaxrefl._errors import JaxreflError
from jaxrefl._jsonsafe import report_json

from ._export import read_maps
from ._job import CaptureFit, FitJob
from ._plan import INFORMED_GAIN, Plan
from ._pooled import PoolChoice

__all__ = ["read_fit", "write_plan"]

_CRITERION = {
    "variance": "expected reduction of the predictive variance of renderings at the "
    "candidates, summed over pixels, renderings and channels, as a share of its value",
    "log_variance": "expected reduction of the predictive variance of renderings at the "
    "candidates, pixel by pixel: the mean over pixels of ln(variance before / after)",
    "information": "expected information gain about the fit's parameters, "
    "0.5 ln det(I + Sigma F) in nats",
}
_NOISES = {"gaussian": fit.GaussianNoise, "shot": fit.ShotNoise, "level": fit.LevelNoise}
_LOSSES = {"l2": fit.L2, "huber": fit.Huber, "cauchy": fit.Cauchy}


def _option(table: dict[str, Any], data: dict[str, Any] | None, where: str):
    if data is None:
        return None
    kind = data.get("type")
    if kind not in table:
        raise JaxreflError(f"{where}: unknown type {kind!r}; expected one of {sorted(table)}")
    args = {k: (np.asarray(v) if isinstance(v, list) else v) for k, v in data.items()}
    args.pop("type")
    return table[kind](**args)


def _job(report: dict[str, Any], where: Path) -> FitJob:
    j = report["job"]
    cfg = j["config"]
    config = fit.FitConfig(
        noise=_option(_NOISES, cfg.get("noise"), f"{where}: job.config.noise"),
        loss=_option(_LOSSES, cfg.get("loss"), f"{where}: job.config.loss"),
        dtype=cfg.get("dtype") or "float32",
    )
    return FitJob(
        model=report["model"],
        holdout=tuple(j.get("holdout", ())),
        tile_pixels=int(j.get("tile_pixels", 4096)),
        config=config,
        alpha_min=j.get("alpha_min"),
        tilt_std=float(j.get("tilt_std", 0.1)),
    )


def _theta(job: FitJob, maps: dict[str, np.ndarray], report: dict[str, Any], pooled, channels):
    from jaxrefl.io import map_name

    from ._models import capture_model

    _model, space = capture_model(
        job.model,
        channels=channels,
        alpha_min=report.get("alpha_min"),
        alpha=None if pooled is None else pooled.alpha,
    )
    labels = space.labels
    h, w = maps["status"].shape
    nat: dict[str, np.ndarray] = {}
    for b in space.blocks:
        cols = [
            np.asarray(maps[map_name(lab)], np.float64).reshape(-1)
            for lab in labels[b.start : b.stop]
        ]
        v = np.stack(cols, -1)
        nat[b.name] = v[:, 0] if b.shape == () else v
    theta = np.asarray(space.from_natural(nat, dtype=job.dtype), np.float64)
    ok = np.all(np.isfinite(theta), axis=-1)
    return np.where(ok[:, None], theta, np.nan), labels, h * w


def _capture(report: dict[str, Any], where: Path):
    from jaxrefl.io import load_capture

    cap = report["capture"]
    path = cap.get("path") or cap.get("source")
    if path is None:
        raise JaxreflError(f"{where}: report.json names no capture (capture.path)")
    capture = load_capture(
        Path(path), resolution=cap.get("resolution"), max_photos=cap.get("max_photos")
    )
    if cap.get("selected") is not None:
        capture = capture.select(cap["selected"])
    factor = cap.get("downsample")
    if factor is None:  # an older report: the factor that gives the fitted size
        factor = max(1, capture.shape[1] // int(cap["height"]))
    if factor > 1:
        capture = capture.downsample(int(factor))
    want = (int(cap["photos"]), int(cap["height"]), int(cap["width"]), int(cap["channels"]))
    if tuple(capture.shape) != want:
        raise JaxreflError(
            f"{where}: capture {path} reads as {capture.shape}, the fit was made on {want} "
            "(photos, height, width, channels): refit, or restore the capture folder"
        )
    return capture


def read_fit(fit_dir: str | Path) -> tuple[CaptureFit, Any]:
    """(fit, capture) from the output folder of ``jaxrefl fit`` (module docstring)."""
    folder = Path(fit_dir)
    rpath = folder / "report.json"
    if not rpath.exists():
        raise FileNotFoundError(
            2, f"no report.json in {folder}: give a `jaxrefl fit` output folder"
        )
    report = json.loads(rpath.read_text())
    maps, _meta = read_maps(folder)
    job = _job(report, rpath)
    pd = report.get("pooled")
    pooled = None
    if pd is not None:
        pooled = PoolChoice(
            model=pd["model"],
            alpha=pd["alpha"],
            cv_rmse=pd.get("cv_rmse", {}),
            prior_mean=tuple(pd.get("prior_mean_F0", ())),
            prior_std=tuple(pd.get("prior_std_F0", ())),
            sigma=pd.get("sigma"),
        )
    channels = int(report["capture"]["channels"])
    theta, labels, _n = _theta(job, maps, report, pooled, channels)
    result = CaptureFit(
        maps=maps,
        report=report,
        labels=tuple(labels),
        theta=theta,
        job=job,
        channels=channels,
        alpha_min=report.get("alpha_min"),
        pooled=pooled,
    )
    return result, _capture(report, rpath)


def write_plan(
    plan: Plan, capture, out_dir: str | Path, *, top: int = 3, fit_dir: str | Path | None = None
) -> dict[str, Path]:
    """``plan.json``, ``highlights.png`` and ``positions.png`` in ``out_dir`` (module
    docstring); returns their paths by name."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = {
        "criterion": plan.criterion,
        "criterion_meaning": _CRITERION[plan.criterion]
        + " (linearised at the fit: Fisher information of the new photo with Tobit censoring "
        "at saturation; shared parameters counted once; jaxrefl.svbrdf.plan_next)",
        "light": plan.light,
        "candidates": plan.candidates.kind,
        "ranking": plan.ranking(),
        "pixels": plan.pixels,
        "pixels_sampled": plan.pixels_sampled,
        "shared": list(plan.shared),
        "informed_gain": INFORMED_GAIN,
        "units": {
            "position": "capture units (cm), sample frame: origin its centre, +z its normal",
            "gain": "the criterion's: variance, a share; log_variance, a mean log ratio; "
            "information, nats",
            "variance_reduction": "share of the reference renderings' predictive variance",
            "log_variance_reduction": "mean over pixels of ln(predictive variance before / after)",
            "information": "nats (the posterior volume shrinks by exp(-information))",
        },
        "fit": None if fit_dir is None else str(fit_dir),
        "capture": None if capture.source is None else str(capture.source),
    }
    paths = {"plan": out / "plan.json"}
    paths["plan"].write_text(report_json(doc))
    paths["highlights"] = _highlights_png(plan, capture, out / "highlights.png", top)
    paths["positions"] = _positions_png(plan, capture, out / "positions.png")
    return paths


def _highlights_png(plan: Plan, capture, path: Path, top: int) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    img = np.nanmean(np.asarray(capture.images, np.float64), axis=0)
    img = np.clip(img / max(float(np.nanpercentile(img, 99)), 1e-12), 0, 1) ** (1 / 2.2)
    half = plan.side / 2
    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    ax.imshow(img, extent=(-half, half, -half, half), origin="upper")
    colours = plt.get_cmap("autumn")(np.linspace(0, 0.8, max(top, 1)))
    for r, m in enumerate(plan.order[:top]):
        x, y = plan.highlight[m]
        rad = max(float(plan.highlight_radius[m]), 0.02 * plan.side)
        ax.add_patch(Circle((x, y), rad, fill=False, lw=2, color=colours[r]))
        label = f"{r + 1}" + (
            f" (photo {plan.candidates.photos[m]})" if plan.candidates.photos else ""
        )
        ax.annotate(
            label, (x, y), color=colours[r], ha="center", va="center", fontsize=11, weight="bold"
        )
    # Wide enough to show a highlight that falls beside the sample.
    shown = plan.order[:top]
    reach = max(
        half * 1.2,
        *(np.abs(plan.highlight[shown]).max(axis=-1) + plan.highlight_radius[shown] + 1.0),
    )
    ax.set_xlim(-reach, reach)
    ax.set_ylim(-reach, reach)
    ax.add_patch(plt.Rectangle((-half, -half), 2 * half, 2 * half, fill=False, lw=1, color="k"))
    ax.set_xlabel(f"x ({capture.unit})")
    ax.set_ylabel(f"y ({capture.unit})")
    ax.set_title(f"where the highlight of the {top} best candidates falls")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _positions_png(plan: Plan, capture, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cand = plan.candidates
    fig, ax = plt.subplots(figsize=(6, 5.2))
    sc = ax.scatter(cand.camera_pos[:, 0], cand.camera_pos[:, 1], c=plan.gain, cmap="viridis", s=60)
    label = {
        "variance": "expected share of the predictive variance removed",
        "log_variance": "expected reduction of the predictive variance of renderings at the "
        "candidates, pixel by pixel: the mean over pixels of ln(variance before / after)",
        "information": "expected information gain (nats)",
    }[plan.criterion]
    fig.colorbar(sc, ax=ax, label=label)
    ax.scatter(
        capture.camera_pos[:, 0],
        capture.camera_pos[:, 1],
        marker="x",
        c="k",
        s=40,
        label="fitted photos",
    )
    b = plan.best
    ax.scatter(
        cand.camera_pos[b, 0],
        cand.camera_pos[b, 1],
        marker="*",
        s=300,
        facecolor="none",
        edgecolor="r",
        lw=2,
        label="best",
    )
    half = plan.side / 2
    ax.add_patch(plt.Rectangle((-half, -half), 2 * half, 2 * half, fill=False, lw=1, color="grey"))
    ax.set_aspect("equal")
    ax.set_xlabel(f"x ({capture.unit})")
    ax.set_ylabel(f"y ({capture.unit})")
    ax.set_title("camera positions seen from above, coloured by gain")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
