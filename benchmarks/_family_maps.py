"""Uncertainty maps of the capture family and the real captures, one row per capture.

Each capture goes through :func:`jaxrefl.svbrdf.uncertainty_maps` with its defaults, the
path ``jaxrefl sample CAPTURE`` takes (``auto`` model, the defaults of
:class:`jaxrefl.posterior.AdaptiveOptions`, population priors, a second pass above R-hat
1.05): the generated members of ``benchmarks/capture_family.py`` (their light written at
the lens, as a user's layout says, whatever the true flash offset) and the real
``bath_tile`` and ``yellow_box``. Printed per capture: the model chosen, the stage times
(the fit with its model choice, the MCMC first and second passes, the whole call), the MCMC
pixel count and the share of them with max R-hat <= 1.05 and, for the generated captures,
the share of pixels whose 90% interval covers the truth, per parameter (albedo R, F0 R,
alpha), over all pixels and split by the fit's misspecification flag. The targets: at most
120 s a map with the compile cache warm, 180 s cold; R-hat <= 1.05 on 99% of the MCMC
pixels; coverage 85-95%.

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
    light: str | None = None,
) -> list[list[object]]:
    """One map per capture; prints a table (module docstring) and returns its rows.
    ``light``: the fit's ``FitJob.light`` (None: the library's default)."""
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
    light_used = svbrdf.FitJob().light if light is None else light
    rows = []
    for name, cap, truth in caps:
        k, h, w, _c = cap.shape
        t0, c0 = time.perf_counter(), time.process_time()
        job = None
        if light is not None:
            from jaxrefl import fit

            job = svbrdf.FitJob(config=fit.FitConfig(dtype=np.float64), light=light)
        res = svbrdf.uncertainty_maps(cap, job)
        total, cpu = time.perf_counter() - t0, time.process_time() - c0
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
            f"{cpu:.0f}",
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
        reasons = res.map.reasons
        noise = res.fit.report["noise_level"]["why"]
        print(f"{name}: {' | '.join(str(v) for v in row)}; MCMC reasons {reasons}; noise: {noise}")
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
        "CPU s",
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
        "light is written at the lens whatever their true flash offset; the fit's light is "
        f"{light_used!r} (FitJob.light; an estimated light's uncertainty is in the "
        "intervals). The first capture's time includes compiling what the others reuse. CPU s: "
        "the process's CPU time (both cores) during the map, which other work on the machine "
        "slows less than the wall time."
    )
    return rows


def run_family_cli(
    members: list[str] | None = None,
    real: tuple[str, ...] = ("bath_tile", "yellow_box"),
    size: int = 256,
) -> list[list[object]]:
    """``jaxrefl sample CAPTURE`` in a fresh process per run, as a user runs it: each
    capture twice, first with an empty compile cache (cold: every program compiled), then
    again with the cache the first run filled (warm). Prints one row per capture: the two
    wall times, the stage times of the warm run (report.json's ``timings``), its MCMC pixels
    and their share with max R-hat <= 1.05."""
    import json
    import os
    import subprocess
    import tempfile

    from capture_family import write_member

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        caps: list[tuple[str, Path]] = []
        for m in FAMILY:
            if members is None or m.name in members:
                caps.append((m.name, write_member(m, root / m.name)))
        data = shared_data() / "svbrdf_flash"
        for name in real:
            if (data / name).exists():
                caps.append((name, data / name))
        for name, folder in caps:
            cache = root / f"cache_{name}"
            env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache)}
            env.pop("JAXREFL_NO_COMPILE_CACHE", None)
            walls, rep = [], {}
            for run in ("cold", "warm"):
                out = root / f"out_{name}_{run}"
                argv = ["jaxrefl", "sample", str(folder), "--out", str(out), "--quiet"]
                if folder.parent == data:
                    argv += ["--downsample", str(max(1, _native(folder) // size))]
                t0 = time.perf_counter()
                r = subprocess.run(argv, env=env, capture_output=True, text=True)
                walls.append(time.perf_counter() - t0)
                if r.returncode not in (0, 3):
                    print(f"{name} ({run}): exit {r.returncode}\n{r.stderr[-2000:]}")
                    break
                rep = json.loads((out / "report.json").read_text())
            if len(walls) < 2:
                continue
            tm, mc = rep["timings"], rep["uncertainty"]["mcmc"]
            n = mc["pixels"]
            ok = (1 - (mc["pixels_rhat_above_1.05"] + mc["pixels_rhat_nan"]) / n) if n else 1.0
            rows.append(
                [
                    name,
                    f"{rep['height']}x{rep['width']}",
                    rep["model"],
                    f"{walls[0]:.1f}",
                    f"{walls[1]:.1f}",
                    f"{tm['fit_s']:.1f}",
                    f"{tm['posterior_s']:.1f}",
                    f"{tm.get('write_s', 0.0):.1f}",
                    n,
                    f"{100 * ok:.2f}",
                ]
            )
            print(f"{name}: cold {walls[0]:.1f} s, warm {walls[1]:.1f} s", flush=True)
    head = ["capture", "size", "model", "cold s", "warm s", "warm: fit s", "MCMC s", "write s"]
    print()
    print(table([*head, "MCMC px", "R-hat<=1.05 %"], rows))
    print(
        f"\n`jaxrefl sample CAPTURE --out OUT --quiet` in a fresh process, wall time from start "
        f"to exit: cold with an empty compile cache, warm with the cache the cold run filled. "
        f"Targets: {TARGET_WARM_S:.0f} s warm, {TARGET_COLD_S:.0f} s cold."
    )
    return rows


def _native(folder: Path) -> int:
    """The side of a real capture's photos as ``load_capture`` reads them by default."""
    from jaxrefl.io import load_capture

    return load_capture(folder).shape[1]
