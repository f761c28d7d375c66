"""Phone photos to a capture: tag corner accuracy by refinement, and the whole way to a fit.

    python benchmarks/marker_detection.py [--views 9] [--supersample 6] [--fit-size 64]
                                          [--no-fit] [--no-write]

Photos are rendered by :func:`jaxrefl.phone.render_photo`: the printed frame (side 17 cm)
with the smooth GGX sample of :func:`jaxrefl.phone.default_sample` 1 mm below it, through
a 640 x 480 pinhole camera (f 520 px, principal point off centre, k1 = -0.12, k2 = 0.05)
held at ``--views`` hand-held positions 25-29 cm up, flash at the lens, written as sRGB
JPEGs (quality 95, 4:4:4).

1. *Corner accuracy*: each refinement of :class:`jaxrefl.phone.Refinement` on the same
   photos, rendered with ``--supersample`` x ``--supersample`` samples per pixel so that
   the edges themselves are exact to a few hundredths of a pixel: distance between detected
   and true corners (RMS, median, 95th percentile, max, px), tags found, time per photo.
   The library's default is the row with the smallest RMS.
2. *Capture*: :func:`jaxrefl.phone.photos_to_capture` on photos rendered with 2 x 2 samples
   (as the tests do): camera position error (mm), reprojection error (px), and rectified
   photos against the sample rendered directly at their pixel centres from the true
   positions (RMS of the linear difference over the mean reference value).
3. *Fit*: ``svbrdf.fit_capture`` (model ``ggx``) on that capture at ``--fit-size`` pixels
   and on the directly rendered capture (the same positions, 8-bit sRGB PNGs): median
   errors of the recovered maps against the truth.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import run_and_record, table

SIDE, DEPTH = 17.0, 0.1
LENS = {"f": 520.0, "cx": 323.1, "cy": 238.4, "k1": -0.12, "k2": 0.05}
EXIF = {0x829A: (1, 60), 0x8827: 100, 0x829D: (18, 10), 0x0112: 1}


def _cameras(n: int, seed: int = 0):
    from jaxrefl.phone import PhoneCamera

    rng = np.random.default_rng(seed)
    ring = [(0.0, 0.0)] + [
        (6.5 * np.cos(a), 6.5 * np.sin(a)) for a in np.linspace(0, 2 * np.pi, n - 1, False)
    ]
    return [
        PhoneCamera(
            position=(ox + rng.normal(0, 0.5), oy + rng.normal(0, 0.5), 27 + rng.normal(0, 1)),
            look_at=(rng.normal(0, 0.8), rng.normal(0, 0.8), 0.0),
            roll=rng.normal(0, 8),
            **LENS,
        )
        for ox, oy in ring[:n]
    ]


def _render(folder: Path, cams, supersample: int) -> list[Path]:
    from jaxrefl.phone import FrameLayout, default_sample, render_photo, write_jpeg

    layout, sample = FrameLayout(SIDE), default_sample()
    folder.mkdir(parents=True, exist_ok=True)
    return [
        write_jpeg(
            folder / f"IMG_{k:04d}.jpg",
            render_photo(cam, layout, sample, depth=DEPTH, supersample=supersample),
            EXIF,
        )
        for k, cam in enumerate(cams)
    ]


def corner_accuracy(files, cams) -> tuple[str, dict]:
    import cv2

    from jaxrefl.phone import (
        DetectorOptions,
        FrameLayout,
        Refinement,
        corner_pixels,
        detect_markers,
    )
    from jaxrefl.scene import SRGBResponse

    layout = FrameLayout(SIDE)
    rows, rms_by = [], {}
    for ref in Refinement:
        errs, found, secs = [], 0, 0.0
        for f, cam in zip(files, cams, strict=True):
            rgb = cv2.imread(str(f))[..., ::-1]
            gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
            lin = np.asarray(SRGBResponse().invert(rgb / 255.0)) @ [0.2126, 0.7152, 0.0722]
            t0 = time.perf_counter()
            det = detect_markers(gray, DetectorOptions(refinement=ref), lin)
            secs += time.perf_counter() - t0
            found += det.count
            truth = corner_pixels(cam, layout)[det.ids]
            errs.append(np.linalg.norm(det.corners - truth, axis=-1).ravel())
        e = np.concatenate(errs)
        rms_by[ref.name] = float(np.sqrt(np.mean(e**2)))
        rows.append(
            [
                ref.name,
                f"{rms_by[ref.name]:.3f}",
                f"{np.median(e):.3f}",
                f"{np.percentile(e, 95):.3f}",
                f"{e.max():.3f}",
                f"{found}/{16 * len(files)}",
                f"{1e3 * secs / len(files):.0f}",
            ]
        )
    headers = ["refinement", "RMS px", "median px", "p95 px", "max px", "tags", "ms/photo"]
    return table(headers, rows), rms_by


def capture_and_fit(tmp: Path, cams, fit_size: int | None) -> str:
    from jaxrefl.io import load_capture, save_generic_capture
    from jaxrefl.phone import (
        CaptureOptions,
        FrameLayout,
        default_sample,
        photos_to_capture,
        render_sample,
    )

    layout, sample = FrameLayout(SIDE), default_sample()
    files = _render(tmp / "raw2", cams, 2)
    size = fit_size or 128
    t0 = time.perf_counter()
    res = photos_to_capture(
        files[0].parent, tmp / "cap", CaptureOptions(side=SIDE, depth=DEPTH, size=size)
    )
    t_cap = time.perf_counter() - t0
    truth_pos = np.array([c.position for c in cams]) + np.array([0.0, 0.0, DEPTH])
    pos_mm = 10 * np.linalg.norm(res.positions - truth_pos, axis=1)
    cap = load_capture(res.out)
    refs = [render_sample(np.array(c.position), layout, sample, size, depth=DEPTH) for c in cams]
    rel = [
        np.sqrt(np.mean((np.asarray(cap.images[i], np.float64) - r) ** 2)) / r.mean()
        for i, r in enumerate(refs)
    ]
    k = res.calibration.intrinsics.camera_matrix
    lines = [
        table(
            [
                "photos",
                "camera position error mm (max / mean)",
                "reprojection px (max / mean)",
                "rectified rel. RMSE % (max / mean)",
                "focal px (true 520)",
                "capture s",
            ],
            [
                [
                    len(cams),
                    f"{pos_mm.max():.3f} / {pos_mm.mean():.3f}",
                    f"{res.calibration.errors.max():.3f} / {res.calibration.errors.mean():.3f}",
                    f"{100 * max(rel):.2f} / {100 * np.mean(rel):.2f}",
                    f"{k[0, 0]:.2f}",
                    f"{t_cap:.1f}",
                ]
            ],
        )
    ]
    if fit_size is None:
        return "\n".join(lines)
    from jaxrefl.svbrdf import FitJob, fit_capture

    direct = tmp / "direct"
    save_generic_capture(
        direct,
        np.stack(refs),
        side=layout.sample_side,
        light_power=1500.0,
        camera_pos=truth_pos,
        light_pos=truth_pos,
        transfer="srgb",
        file_format="png8",
    )
    from jaxrefl.scene import planar_points

    pts = np.asarray(planar_points(size, size, layout.sample_side), np.float64)
    truth = sample.params_at(pts[..., :2])
    rows = []
    for name, path in (("phone photos -> jaxrefl capture", res.out), ("direct render", direct)):
        t0 = time.perf_counter()
        fit = fit_capture(load_capture(path), FitJob(model="ggx"), tmp / f"fit-{path.name}")
        m = fit.maps
        alb = np.stack([m["albedo.R"], m["albedo.G"], m["albedo.B"]], -1)
        rows.append(
            [
                name,
                f"{np.median(np.abs(alb - truth['albedo'])):.4f}",
                f"{np.median(np.abs(m['specular'] - truth['specular'][..., 0])):.4f}",
                f"{100 * np.median(np.abs(m['roughness'] / np.sqrt(truth['alpha']) - 1)):.2f}",
                f"{time.perf_counter() - t0:.0f}",
            ]
        )
    lines += [
        "",
        f"Fit (model ggx, {size} x {size}, {len(cams)} photos), recovered maps against the truth:",
        "",
        table(
            [
                "capture",
                "albedo median abs err",
                "F0 median abs err",
                "roughness median rel err %",
                "fit s",
            ],
            rows,
        ),
    ]
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--views", type=int, default=9)
    p.add_argument("--supersample", type=int, default=6)
    p.add_argument("--fit-size", type=int, default=64)
    p.add_argument("--no-fit", action="store_true")
    a = p.parse_args()
    cams = _cameras(a.views)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        files = _render(tmp / "raw", cams, a.supersample)
        text, rms = corner_accuracy(files, cams)
        print(f"### Corner accuracy ({a.views} photos, {a.supersample}^2 samples per pixel)\n")
        print(text)
        print(f"\nsmallest RMS: {min(rms, key=rms.get)}\n")
        print("### Capture\n")
        print(capture_and_fit(tmp, cams, None if a.no_fit else a.fit_size))
    return 0


if __name__ == "__main__":
    sys.exit(run_and_record("marker_detection", "Phone photos: tag corners and capture", main))
