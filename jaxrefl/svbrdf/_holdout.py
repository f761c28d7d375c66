"""Validation as an output: leave-one-photo-out over every photo of a capture.

For each photo k in turn, the job is fitted on the other photos (:func:`fit_capture` with
``holdout=(k,)``) and predicts photo k; the baseline model (Lambert by default) is fitted the
same way in the same run, so every figure has its reference beside it. Held-out photos are
weights in the data, not shapes, so every fold after the first reuses the compiled programs
of the first (one compile per model, whatever the photo count); the LM compacts its slow
pixels where the K fits together are large enough to repay the compaction stages' compile
(:data:`~jaxrefl.svbrdf._job_types.COMPACT_MIN_PIXELS` pixels over all folds, where the
job's ``compact`` is None).

Figures (linear radiance, over each held-out photo's uncensored, valid observations, raw
predictions: nothing clipped):

* ``heldout_rmse_per_photo[k]``: RMSE of photo k's prediction by the fit without it;
* ``heldout_rmse``: the mean of those K figures (each photo counts once);
* ``heldout_pixel_rmse_median`` / ``_p99``: per pixel, the RMSE over all its held-out
  observations (every photo, each predicted by the fold that left it out), then the median
  and the 99th percentile over pixels: where the error sits, not only how much there is;
* the same under ``lambert_*`` (or ``<baseline>_*``) for the baseline, and
  ``photos_worse_than_baseline``: the photos whose held-out RMSE exceeds the baseline's;
* ``fold_status_counts`` / ``fold_laplace_flag_counts``: fit statuses and Laplace flags
  summed over the K folds (K x pixels in all): how much of the map is at a bound or not
  identified.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from jaxrefl._errors import JaxreflError

from ._job import fit_capture
from ._job_types import CaptureFit, FitJob

__all__ = ["LeaveOneOut", "leave_one_out"]


@dataclass
class LeaveOneOut:
    """Result of :func:`leave_one_out`: per-photo figures of the job and the baseline.

    per_photo, baseline_per_photo: (K,) held-out RMSE of each photo (NaN without values)
    pixel_rmse, baseline_pixel_rmse: (H, W) per-pixel held-out RMSE over all photos
    fit_s, baseline_fit_s: (K,) run seconds of each fold (compile apart: ``compile_s``)
    report: the figures as ``report.json`` holds them (module docstring)
    """

    job: FitJob
    baseline: str
    per_photo: np.ndarray
    baseline_per_photo: np.ndarray
    pixel_rmse: np.ndarray
    baseline_pixel_rmse: np.ndarray
    fit_s: np.ndarray
    baseline_fit_s: np.ndarray
    compile_s: float
    baseline_compile_s: float
    report: dict[str, Any]


def _fold_errors(fit: CaptureFit, k: int) -> tuple[float, np.ndarray, np.ndarray]:
    """(photo k's RMSE, per-pixel SSE (N,), per-pixel count (N,)) of a fit holding k out."""
    assert fit.sse is not None and fit.cnt is not None  # fit_capture's own result holds them
    sse, cnt = fit.sse[:, k], fit.cnt[:, k]
    n = float(np.sum(cnt))
    rmse = float(np.sqrt(np.sum(sse) / n)) if n > 0 else float("nan")
    return rmse, sse, cnt


def _run(capture, job: FitJob, progress: Callable[[str], None] | None):
    k = capture.n_photos
    per = np.full(k, np.nan)
    secs = np.zeros(k)
    compile_s = 0.0
    h, w = capture.shape[1:3]
    sse = np.zeros(h * w)
    cnt = np.zeros(h * w)
    choices = []
    autos = []
    counts: dict[str, dict[str, int]] = {"status": {}, "laplace_flag": {}}
    # K fits of the capture share their compiled programs: compaction stages repay their
    # compile by the work of all folds together, not by one fit's (FitJob.compacts).
    job = replace(job, compact=job.compacts(k * h * w))
    for i in range(k):
        t0 = time.perf_counter()
        fit = fit_capture(capture, replace(job, holdout=(i,)))
        wall = time.perf_counter() - t0
        compile_s += fit.report["timings"]["compile_s"]
        secs[i] = wall - fit.report["timings"]["compile_s"]
        per[i], s, c = _fold_errors(fit, i)
        sse += s
        cnt += c
        if fit.report.get("pooled") is not None:
            choices.append(fit.report["pooled"])
        if fit.report.get("auto") is not None:
            autos.append(fit.report["auto"])
        for key, src in (("status", "status_counts"), ("laplace_flag", "laplace_flag_counts")):
            for name, v in fit.report[src].items():
                counts[key][name] = counts[key].get(name, 0) + int(v)
        if progress is not None:
            progress(f"{job.model}: photo {i} held out, RMSE {per[i]:.5f} ({wall:.1f} s)")
    with np.errstate(invalid="ignore", divide="ignore"):
        pix = np.where(cnt > 0, np.sqrt(sse / np.maximum(cnt, 1)), np.nan).reshape(h, w)
    return per, pix, secs, compile_s, choices, autos, counts


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _pct(pix: np.ndarray, q: float) -> float | None:
    v = pix[np.isfinite(pix)]
    return float(np.quantile(v, q)) if v.size else None


def leave_one_out(
    capture,
    job: FitJob | None = None,
    *,
    baseline: str = "lambert",
    progress: Callable[[str], None] | None = None,
) -> LeaveOneOut:
    """Fit ``job`` and the ``baseline`` model K times each, every photo held out once
    (module docstring). ``job.holdout`` is ignored. ``progress`` receives one line a fold."""
    job = FitJob() if job is None else job
    if capture.n_photos < 2:
        raise JaxreflError("leave-one-out needs at least two photos")
    per, pix, secs, comp, choices, autos, counts = _run(capture, job, progress)
    base_job = replace(job, model=baseline)
    b_per, b_pix, b_secs, b_comp, _, _, _ = _run(capture, base_job, progress)
    tag = baseline
    report: dict[str, Any] = {
        "holdout": "all",
        "heldout_rmse": _finite(np.nanmean(per)) if np.any(np.isfinite(per)) else None,
        "heldout_rmse_per_photo": {str(i): _finite(v) for i, v in enumerate(per)},
        "heldout_pixel_rmse_median": _pct(pix, 0.5),
        "heldout_pixel_rmse_p99": _pct(pix, 0.99),
        f"{tag}_heldout_rmse": _finite(np.nanmean(b_per)) if np.any(np.isfinite(b_per)) else None,
        f"{tag}_heldout_rmse_per_photo": {str(i): _finite(v) for i, v in enumerate(b_per)},
        f"{tag}_heldout_pixel_rmse_median": _pct(b_pix, 0.5),
        f"{tag}_heldout_pixel_rmse_p99": _pct(b_pix, 0.99),
        "photos_worse_than_baseline": [int(i) for i in np.flatnonzero(per > b_per)],
        "baseline": tag,
        "fold_fit_s": [float(s) for s in secs],
        "fold_compile_s": comp,
        f"{tag}_fold_fit_s": [float(s) for s in b_secs],
        "fold_status_counts": counts["status"],
        "fold_laplace_flag_counts": counts["laplace_flag"],
    }
    if choices:
        report["pooled_per_fold"] = choices
    if autos:
        report["auto_per_fold"] = autos
    return LeaveOneOut(
        job=job,
        baseline=tag,
        per_photo=per,
        baseline_per_photo=b_per,
        pixel_rmse=pix,
        baseline_pixel_rmse=b_pix,
        fit_s=secs,
        baseline_fit_s=b_secs,
        compile_s=comp,
        baseline_compile_s=b_comp,
        report=report,
    )
