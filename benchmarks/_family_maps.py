"""Uncertainty maps of the capture family and the real captures, one row per capture.

Each capture goes through :func:`jaxrefl.svbrdf.uncertainty_maps` with its defaults, the
path ``jaxrefl sample CAPTURE`` takes (``auto`` model, :data:`jaxrefl.posterior.MAP_OPTIONS`,
population priors, a second pass above R-hat 1.05): the generated members of
``benchmarks/capture_family.py`` (their light written at the lens, as a user's layout says,
whatever the true flash offset) and the real ``bath_tile`` and ``yellow_box``. Printed per
capture: the model chosen, the stage times (the fit with its model choice, the MCMC first
and second passes, the whole call), the MCMC pixel count and the share of them with max
R-hat <= 1.05 and, for the generated captures, the share of pixels whose 90% interval
covers the truth, per parameter (albedo R, F0 R, alpha), over all pixels and split by the
fit's misspecification flag. The targets (issue 45): at most 120 s a map with the compile
cache warm, 180 s cold; R-hat <= 1.05 on 99% of the MCMC pixels; coverage 85-95%.

``posterior_speed.py --only-family`` and ``predictive_coverage.py --only-family`` both run
it (their sections of docs/benchmarks.md get the same table).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import flash_capture, shared_data, table
from capture_family import FAMILY, render_member

TARGET_WARM_S = 120.0
TARGET_COLD_S = 180.0
COVER = ("albedo.R", "specular.R", "alpha")  # the parameters whose coverage is printed


def _coverage(res, truth: dict[str, np.ndarray], mask: np.ndarray) -> list[str]:
    """Share of ``mask``'s pixels whose 90% interval (q05, q95) covers the truth, per
    :data:`COVER` entry (the grey models' ``specular`` against the truth's R channel)."""
    u = res.map
    labels = list(u.labels)
    out = []
    for lab in COVER:
        name, _, ch = lab.partition(".")
        if lab not in labels and name not in labels:
            out.append("-")  # the model does not sample it (lambert; pooled's shared lobe)
            continue
        j = labels.index(lab) if lab in labels else labels.index(name)
        t = truth[name]
        t = t[..., "RGB".index(ch)] if ch else t
        t = t.reshape(-1)
        lo, hi = u.q05[:, j], u.q95[:, j]
        ok = mask & np.isfinite(lo) & np.isfinite(hi)
        out.append(
            f"{100 * np.mean((lo[ok] <= t[ok]) & (t[ok] <= hi[ok])):.1f}" if ok.any() else "-"
        )
    return out


def run_family(
    members: list[str] | None = None,
    real: tuple[str, ...] = ("bath_tile", "yellow_box"),
    size: int = 256,
) -> list[list[object]]:
    """One map per capture; prints a table (module docstring) and returns its rows."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxrefl import svbrdf

    caps = []
    for m in FAMILY:
        if members is None or m.name in members:
            r = render_member(m)
            caps.append(
                (f"{m.name} ({m.flash_offset_cm:g} cm, {100 * m.noise:g}%)", r.capture(), r.truth)
            )
    root = shared_data()
    for name in real:
        if (root / "svbrdf_flash" / name).exists():
            caps.append((name, flash_capture(name, size), None))
        else:
            print(f"(no {root / 'svbrdf_flash' / name}: {name} left out)")
    rows = []
    for name, cap, truth in caps:
        k, h, w, _c = cap.shape
        t0 = time.perf_counter()
        res = svbrdf.uncertainty_maps(cap)
        total = time.perf_counter() - t0
        tm, mt = res.timings, res.map.timings
        mc = res.map.report()["mcmc"]
        n = mc["pixels"]
        ok = (
            100 * (1 - (mc["pixels_rhat_above_1.05"] + mc["pixels_rhat_nan"]) / n)
            if n
            else float("nan")
        )
        row: list[object] = [
            name,
            f"{h}x{w}",
            k,
            res.model + (" (widened)" if "widened" in res.model_choice else ""),
            f"{tm['fit_s']:.1f}",
            n,
            f"{mt.get('mcmc_wall_s', 0.0):.1f}",
            mt.get("rerun_pixels", 0),
            f"{mt.get('rerun_wall_s', 0.0):.1f}",
            f"{total:.1f}",
            f"{ok:.2f}",
        ]
        if truth is not None:
            flagged = res.fit.maps["misspecified"].reshape(-1) != 0
            every = np.ones(h * w, bool)
            row += ["/".join(_coverage(res, truth, sel)) for sel in (every, ~flagged, flagged)]
            row.append(int(flagged.sum()))
        else:
            row += ["-", "-", "-", "-"]
        rows.append(row)
        print(f"{name}: {total:.1f} s", flush=True)
    head = [
        "capture",
        "size",
        "photos",
        "model",
        "fit s",
        "MCMC px",
        "MCMC s",
        "2nd px",
        "2nd s",
        "total s",
        "R-hat<=1.05 %",
        "cover all %",
        "cover unflagged %",
        "cover flagged %",
        "flagged px",
    ]
    print()
    print(table(head, rows))
    print(
        f"\ncoverage: share of pixels whose 90% interval covers the truth, {' / '.join(COVER)}; "
        "flagged: the fit's misspecification map (docs/outputs.md). Targets: a map within "
        f"{TARGET_WARM_S:.0f} s (compile cache warm) / {TARGET_COLD_S:.0f} s (cold), "
        "R-hat <= 1.05 on 99% of the MCMC pixels, coverage 85-95%. The generated captures' "
        "light is written at the lens whatever their true flash offset (the model does not "
        "know it). The first capture's time includes compiling what the others reuse."
    )
    return rows
