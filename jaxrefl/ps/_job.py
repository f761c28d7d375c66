"""Run a photometric-stereo method on a capture folder and write its outputs.

:func:`solve_capture` maps a method over the masked pixels of a :class:`PSCapture` and
returns image-shaped maps; :func:`run_ps` is what ``jaxrefl ps`` does:

    OUT/normals.exr   normal.X, normal.Y, normal.Z (camera frame of :mod:`jaxrefl.ps`,
                      NaN where there is no estimate) and ``status`` (jaxrefl.fit.Status)
    OUT/normals.png   RGB = (n + 1) / 2 in 8 bits (black where there is no estimate)
    OUT/albedo.exr    albedo.R/G/B (rho: I = E rho n.l), and albedo.png (scaled to its
                      99th percentile)
    OUT/depth.exr     Z, Poisson integration on the mask (pixel units, mean 0), and
                      depth.png (min-max scaled grey)
    OUT/error.exr     error_deg (angle to the reference normals), and error.png (grey,
                      0..30 degrees), when there is a reference: the ground truth of the
                      capture, or with ``reference="sphere"`` the ideal sphere fitted to
                      the mask
    OUT/report.json   method, capture, mean/median angular error (null without a
                      reference), status counts, light calibration, timings in seconds
                      (``solve_s`` includes JIT compilation on the first call)

With ``calibrate_lights`` (a chrome-sphere capture folder under the same lights) the
directions are re-estimated from its highlights (:func:`chrome_sphere_lights`) and the
report gives their angle to the capture's own lights.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl._jsonsafe import report_json
from jaxrefl.fit import Status, describe, has_estimate

from ._capture import PSCapture, PSInputError
from ._eval import angular_error, error_stats
from ._integrate import poisson
from ._io import load_capture
from ._lights import chrome_sphere_lights
from ._methods import LeastSquares, PSMethod
from ._sphere import fit_circle, sphere_normals

__all__ = ["run_ps", "solve_capture"]


def _check_method(method: PSMethod) -> None:
    if not isinstance(method, PSMethod):
        raise TypeError(
            f"method must be a PS method object (ps.LeastSquares(), ps.Robust(), "
            f"ps.NormalBRDF(); ps.METHODS[name]() by name), not {method!r}"
        )


def solve_capture(cap: PSCapture, method: PSMethod = LeastSquares()) -> dict[str, np.ndarray]:
    """Maps of one method: normals (H, W, 3), albedo (H, W, C), status (H, W) int32
    (MASKED outside the mask), n_used (H, W)."""
    _check_method(method)
    obs, ok = cap.pixels()
    w = ok.astype(obs.dtype)
    sat = obs >= 1.0  # the top code: censored (by the methods that model censoring)
    r = method.solve(obs, cap.lights, cap.intensities, w, sat)
    h, wd = cap.shape
    c = obs.shape[-1]
    normals = np.full((h, wd, 3), np.nan, np.float32)
    albedo = np.full((h, wd, c), np.nan, np.float32)
    status = np.full((h, wd), int(Status.MASKED), np.int32)
    n_used = np.zeros((h, wd), np.int32)
    normals[cap.mask] = np.asarray(r.normals)
    albedo[cap.mask] = np.asarray(r.albedo)
    status[cap.mask] = np.asarray(r.status)
    n_used[cap.mask] = np.asarray(r.n_used)
    return {"normals": normals, "albedo": albedo, "status": status, "n_used": n_used}


def _png8(a: np.ndarray) -> np.ndarray:
    return np.round(np.clip(np.nan_to_num(a), 0.0, 1.0) * 255).astype(np.uint8)


def _num(x) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def run_ps(
    capture_dir: str | Path,
    out_dir: str | Path,
    method: PSMethod = LeastSquares(),
    calibrate_lights: str | Path | None = None,
    reference: str | None = None,
    downsample: int = 1,
) -> dict:
    """Load, (calibrate), solve, integrate, evaluate and write (module docstring); returns
    the report."""
    from jaxrefl.io import write_exr, write_png

    _check_method(method)
    if reference not in (None, "sphere"):
        raise JaxreflError(f"reference must be 'sphere' or None, not {reference!r}")
    if downsample < 1:
        raise JaxreflError(f"downsample must be >= 1, got {downsample}")
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    cap = load_capture(capture_dir).downsample(downsample)
    timings["load_s"] = time.perf_counter() - t0
    report: dict = {
        "capture": str(capture_dir),
        "name": cap.name,
        "method": method.kind,
        "method_options": method.to_json(),
        "image_size": [int(cap.shape[1]), int(cap.shape[0])],
        "n_images": int(cap.images.shape[0]),
        "n_pixels": int(cap.mask.sum()),
        "downsample": int(downsample),
        "lights": "capture",
    }
    if calibrate_lights is not None:
        t = time.perf_counter()
        chrome = load_capture(calibrate_lights).downsample(downsample)
        if chrome.images.shape[0] != cap.images.shape[0]:
            raise PSInputError(
                calibrate_lights,
                f"{chrome.images.shape[0]} chrome images for {cap.images.shape[0]} capture images",
            )
        cal = chrome_sphere_lights(chrome.images, chrome.mask, names=[f.name for f in chrome.files])
        err = cal.error_deg(cap.lights)
        report["lights"] = "chrome_sphere"
        report["light_calibration"] = {
            **cal.to_dict(),
            "error_vs_capture_lights_deg": err.tolist(),
            "mean_error_vs_capture_lights_deg": float(err.mean()),
        }
        cap = cap.with_lights(cal.directions, cap.intensities)
        timings["calibrate_s"] = time.perf_counter() - t
    t = time.perf_counter()
    maps = solve_capture(cap, method)
    timings["solve_s"] = time.perf_counter() - t
    has = has_estimate(maps["status"])
    t = time.perf_counter()
    depth = poisson(maps["normals"], has) if has.any() else np.full(cap.shape, np.nan)
    timings["integrate_s"] = time.perf_counter() - t
    gt, ref_name = cap.normals_gt, "ground_truth" if cap.normals_gt is not None else None
    if reference == "sphere":
        gt, _ = sphere_normals(cap.shape, fit_circle(cap.mask, "capture mask"))
        ref_name = "fitted_sphere"
    report["reference"] = ref_name
    report["status_counts"] = describe(maps["status"][cap.mask])
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    n = maps["normals"]
    write_exr(
        out / "normals.exr",
        {
            "normal.X": n[..., 0],
            "normal.Y": n[..., 1],
            "normal.Z": n[..., 2],
            "status": maps["status"].astype(np.uint32),
        },
        metadata={"frame": "camera: x right, y up, z towards the camera", "method": method.kind},
    )
    write_png(out / "normals.png", _png8(np.where(has[..., None], (n + 1) / 2, 0.0)))
    alb = maps["albedo"]
    names = ["R", "G", "B"] if alb.shape[-1] == 3 else [f"c{i}" for i in range(alb.shape[-1])]
    write_exr(out / "albedo.exr", {f"albedo.{c}": alb[..., i] for i, c in enumerate(names)})
    top = np.nanpercentile(alb[has], 99) if has.any() else 1.0
    alb8 = _png8(alb / (top if top > 0 else 1.0))
    write_png(out / "albedo.png", alb8 if alb8.shape[-1] in (1, 3) else alb8[..., :1])
    write_exr(out / "depth.exr", {"Z": depth.astype(np.float32)})
    zr = depth[has]
    span = (zr.max() - zr.min()) if zr.size else 1.0
    z8 = (depth - (zr.min() if zr.size else 0.0)) / (span if span > 0 else 1.0)
    write_png(out / "depth.png", _png8(z8))
    if gt is not None:
        ref_ok = cap.mask & np.all(np.isfinite(gt), axis=-1)
        err = np.where(ref_ok, angular_error(n, gt), np.nan)
        stats = error_stats(err, ref_ok)
        write_exr(out / "error.exr", {"error_deg": err.astype(np.float32)})
        write_png(out / "error.png", _png8(err / 30.0))
        report["mean_angular_error_deg"] = _num(stats.mean)
        report["median_angular_error_deg"] = _num(stats.median)
        report["p90_angular_error_deg"] = _num(stats.p90)
        report["n_compared"] = stats.n_pixels
        report["n_missing"] = stats.n_missing
    else:
        report["mean_angular_error_deg"] = None
        report["median_angular_error_deg"] = None
    timings["write_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t0
    report["timings"] = timings
    (out / "report.json").write_text(report_json(report))
    return report
