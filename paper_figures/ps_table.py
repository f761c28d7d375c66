"""Photometric stereo on the real UW psm captures: angular errors, light calibration, times.

    python paper_figures/ps_table.py [--data ../shared/data] [--brdf-downsample 2]

Writes paper_figures/ps_table.csv and paper_figures/ps_table.png. Data: UW CSE 455
photometric-stereo images (courtesy S. Seitz), ``../shared/data/photometric_stereo/uw_psm``.

* Gray sphere (matte), against the ideal sphere fitted to its mask: every calibrated
  method with the given ``lights.txt``; least squares with chrome-calibrated lights;
  uncalibrated PS (rank-3 SVD of gray sphere + buddha stacked, the linear/GBR ambiguity
  resolved by the gray sphere's known normals).
* Objects (buddha, cat) have no ground truth. Checks that are possible: the relative RMS
  of the Lambertian re-rendering I = E rho max(n.l, 0) with each method's normals and
  albedo over the usable lit observations (``lambert_rerender_rel_rms``; for ``brdf`` this
  leaves out its specular lobe, so it is an upper bound of its own fit residual), and the
  angle between the normals of two methods.
* Chrome sphere: light directions from its highlights against ``lights.txt``; also from
  the gray sphere's shading (Lambertian calibration), and the two against each other.
* Times: wall seconds of the solve, warm (second call, compiled) and first call (with JIT
  compilation), on this machine (CPU).
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import time
from pathlib import Path

import numpy as np

from jaxrefl import ps

HERE = Path(__file__).resolve().parent
FIELDS = [
    "section",
    "capture",
    "method",
    "lights",
    "reference",
    "downsample",
    "n_pixels",
    "mean_deg",
    "median_deg",
    "p90_deg",
    "check",
    "check_value",
    "solve_warm_s",
    "solve_first_s",
]


def _timed(cap, method):
    t = time.perf_counter()
    maps = ps.solve_capture(cap, ps.METHODS[method]())
    first = time.perf_counter() - t
    t = time.perf_counter()
    maps = ps.solve_capture(cap, ps.METHODS[method]())
    return maps, time.perf_counter() - t, first


def _rerender_rms(cap, maps):
    """Relative RMS of the Lambertian prediction over usable, lit observations."""
    m = cap.mask & (maps["status"] < 4)
    n = maps["normals"][m]
    rho = maps["albedo"][m]
    obs = np.moveaxis(cap.images[:, m], 0, 1)
    ok = np.moveaxis(cap.usable[:, m], 0, 1)
    cos = np.maximum(n @ cap.lights.T, 0.0)
    pred = cap.intensities[None] * rho[:, None, :] * cos[..., None]
    lit = ok & (cos[..., None] > 0)
    r = (obs - pred)[lit]
    return float(np.sqrt(np.mean(r * r)) / np.sqrt(np.mean(obs[lit] ** 2)))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = os.environ.get("JAXREFL_SHARED_DATA", str(HERE.parent.parent / "shared" / "data"))
    p.add_argument("--data", type=Path, default=Path(default))
    p.add_argument("--brdf-downsample", type=int, default=2)
    args = p.parse_args()
    uw = args.data / "photometric_stereo" / "uw_psm"
    rows = []

    def row(**kw):
        r = {f: "" for f in FIELDS}
        r.update(kw)
        rows.append(r)
        print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items() if v != ""})

    gray = ps.load_uw(uw / "gray")
    chrome = ps.load_uw(uw / "chrome")
    circle = ps.fit_circle(gray.mask)
    maps_all = {}
    # ------------------------------------------------------------------ gray sphere
    for method in ps.METHODS:
        ds = args.brdf_downsample if method == "brdf" else 1
        cap = gray.downsample(ds)
        maps, warm, first = _timed(cap, method)
        maps_all[("gray", method)] = (cap, maps)
        _, st, _ = ps.sphere_error(maps["normals"], cap.mask)
        row(
            section="gray sphere",
            capture="gray",
            method=method,
            lights="lights.txt",
            reference="fitted sphere",
            downsample=ds,
            n_pixels=st.n_pixels,
            mean_deg=st.mean,
            median_deg=st.median,
            p90_deg=st.p90,
            check="lambert_rerender_rel_rms",
            check_value=_rerender_rms(cap, maps),
            solve_warm_s=warm,
            solve_first_s=first,
        )
    t = time.perf_counter()
    cal = ps.chrome_sphere_lights(chrome.images, chrome.mask)
    t_cal = time.perf_counter() - t
    gray_c = gray.with_lights(cal.directions)
    for method in ("ls", "robust"):
        maps, warm, first = _timed(gray_c, method)
        _, st, _ = ps.sphere_error(maps["normals"], gray.mask)
        row(
            section="gray sphere",
            capture="gray",
            method=method,
            lights="chrome sphere",
            reference="fitted sphere",
            downsample=1,
            n_pixels=st.n_pixels,
            mean_deg=st.mean,
            median_deg=st.median,
            p90_deg=st.p90,
            solve_warm_s=warm,
            solve_first_s=first,
        )
    # Uncalibrated: gray sphere + buddha in one intensity matrix (same lights and camera).
    buddha = ps.load_uw(uw / "buddha")
    t = time.perf_counter()
    gn, inside = ps.sphere_normals(gray.shape, circle)
    og, okg = gray.pixels()
    ob, okb = buddha.pixels()
    mg, mb = og.mean(-1), ob.mean(-1)
    ii, jj = np.mgrid[: gray.shape[0], : gray.shape[1]]
    rim = np.hypot(ii - circle.row, jj - circle.col) < circle.radius - 3
    sel = (inside & rim)[gray.mask]
    # Rows of the SVD: pixels lit and unsaturated in every image (no shadow, no clipping).
    litg = okg.all(axis=(1, 2)) & (mg.min(1) > 0.02) & sel
    litb = okb.all(axis=(1, 2)) & (mb.min(1) > 0.02)
    res = ps.uncalibrated(
        np.concatenate([mg, mb]),
        np.concatenate([litg, litb]),
        np.concatenate([litg, np.zeros_like(litb)]),
        gn[gray.mask][litg],
    )
    t_unc = time.perf_counter() - t
    err = ps.angular_error(res.normals[: len(mg)], gn[gray.mask])
    st = ps.error_stats(err, sel)
    sv = res.singular_values
    row(
        section="gray sphere",
        capture="gray+buddha",
        method="uncalibrated (SVD, known normals)",
        lights="estimated",
        reference="fitted sphere",
        downsample=1,
        n_pixels=st.n_pixels,
        mean_deg=st.mean,
        median_deg=st.median,
        p90_deg=st.p90,
        check="sv4/sv3",
        check_value=float(sv[3] / sv[2]),
        solve_warm_s=t_unc,
    )
    e_unc = ps.angular_error(res.lights, gray.lights)
    row(
        section="light calibration",
        capture="gray+buddha",
        method="uncalibrated lights",
        lights="estimated",
        reference="lights.txt",
        mean_deg=float(e_unc.mean()),
        median_deg=float(np.median(e_unc)),
        p90_deg=float(np.percentile(e_unc, 90)),
        check="max_deg",
        check_value=float(e_unc.max()),
    )
    # ------------------------------------------------------------------ objects
    for name in ("buddha", "cat"):
        cap0 = buddha if name == "buddha" else ps.load_uw(uw / name)
        normals = {}
        for method in ps.METHODS:
            ds = args.brdf_downsample if method == "brdf" else 1
            cap = cap0.downsample(ds)
            maps, warm, first = _timed(cap, method)
            maps_all[(name, method)] = (cap, maps)
            normals[method] = maps["normals"]
            row(
                section="objects",
                capture=name,
                method=method,
                lights="lights.txt",
                reference="none",
                downsample=ds,
                n_pixels=int(cap.mask.sum()),
                check="lambert_rerender_rel_rms",
                check_value=_rerender_rms(cap, maps),
                solve_warm_s=warm,
                solve_first_s=first,
            )
        for a, b in (("ls", "robust"), ("robust", "brdf")):
            ds = args.brdf_downsample if "brdf" in (a, b) else 1
            na = normals[a][::ds, ::ds] if b == "brdf" else normals[a]
            e = ps.angular_error(na, normals[b])
            st = ps.error_stats(e, np.isfinite(e))
            row(
                section="objects",
                capture=name,
                method=f"{a} vs {b}",
                reference=a,
                downsample=ds,
                n_pixels=st.n_pixels,
                mean_deg=st.mean,
                median_deg=st.median,
                p90_deg=st.p90,
            )
    # Uncalibrated buddha normals against the calibrated robust ones.
    robust_buddha = maps_all[("buddha", "robust")][1]["normals"][buddha.mask]
    e = ps.angular_error(res.normals[len(mg) :], robust_buddha)
    st = ps.error_stats(e, np.isfinite(e))
    row(
        section="objects",
        capture="buddha",
        method="uncalibrated vs robust",
        reference="robust",
        downsample=1,
        n_pixels=st.n_pixels,
        mean_deg=st.mean,
        median_deg=st.median,
        p90_deg=st.p90,
    )
    # ------------------------------------------------------------------ light calibration
    e_ch = cal.error_deg(chrome.lights)
    row(
        section="light calibration",
        capture="chrome",
        method="chrome sphere highlights",
        lights="estimated",
        reference="lights.txt",
        mean_deg=float(e_ch.mean()),
        median_deg=float(np.median(e_ch)),
        p90_deg=float(np.percentile(e_ch, 90)),
        check="mean_std_deg",
        check_value=float(cal.std_deg.mean()),
        solve_warm_s=t_cal,
    )
    t = time.perf_counter()
    lam = ps.lambertian_sphere_lights(gray.images, gray.mask)
    t_lam = time.perf_counter() - t
    e_l = lam.error_deg(gray.lights)
    row(
        section="light calibration",
        capture="gray",
        method="Lambertian sphere shading",
        lights="estimated",
        reference="lights.txt",
        mean_deg=float(e_l.mean()),
        median_deg=float(np.median(e_l)),
        p90_deg=float(np.percentile(e_l, 90)),
        check="mean_std_deg",
        check_value=float(lam.std_deg.mean()),
        solve_warm_s=t_lam,
    )
    e_cl = lam.error_deg(cal.directions)
    row(
        section="light calibration",
        capture="chrome, gray",
        method="Lambertian vs chrome",
        lights="estimated",
        reference="chrome sphere",
        mean_deg=float(e_cl.mean()),
        median_deg=float(np.median(e_cl)),
        p90_deg=float(np.percentile(e_cl, 90)),
    )

    out_csv = HERE / "ps_table.csv"
    with out_csv.open("w", newline="") as f:
        f.write(
            f"# machine: {platform.machine()} {platform.processor() or ''} "
            f"{os.cpu_count()} CPUs; jaxrefl paper_figures/ps_table.py\n"
        )
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})
    print(f"wrote {out_csv}")
    _figure(rows, maps_all, cal, chrome, lam)


def _figure(rows, maps_all, cal, chrome, lam):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 4, figsize=(15, 10.5))
    for c, method in enumerate(ps.METHODS):
        for r, name in enumerate(("gray", "buddha")):
            cap, maps = maps_all[(name, method)]
            n = maps["normals"]
            ax = axes[r, c]
            ax.imshow(np.where(np.isfinite(n), (n + 1) / 2, 0.0))
            ax.set_title(f"{name}: {method} normals", fontsize=9)
            ax.axis("off")
        cap, maps = maps_all[("gray", method)]
        err, st, _ = ps.sphere_error(maps["normals"], cap.mask)
        ax = axes[2, c]
        im = ax.imshow(err, vmin=0, vmax=15, cmap="magma")
        ax.set_title(
            f"gray error vs fitted sphere: {method}\nmean {st.mean:.2f}, "
            f"median {st.median:.2f} deg",
            fontsize=9,
        )
        ax.axis("off")
    fig.colorbar(im, ax=axes[2, :3], fraction=0.02, label="degrees")
    ax = axes[0, 3]
    k = np.arange(len(chrome.lights))
    ax.bar(k - 0.2, cal.error_deg(chrome.lights), 0.4, yerr=cal.std_deg, label="chrome")
    ax.bar(k + 0.2, lam.error_deg(chrome.lights), 0.4, yerr=lam.std_deg, label="Lambertian")
    ax.set_xlabel("light")
    ax.set_ylabel("angle to lights.txt (deg)")
    ax.set_title("light calibration (1-sigma bars)", fontsize=9)
    ax.legend(fontsize=8)
    ax = axes[1, 3]
    ax.axis("off")
    lines = [
        f"{r['capture'][:12]:12s} {r['method'][:26]:26s} {r['lights'][:9]:9s} "
        f"{r['mean_deg']:6.2f} {r['median_deg']:6.2f}"
        for r in rows
        if isinstance(r["mean_deg"], float)
    ]
    ax.text(
        0,
        1,
        "capture      method                     lights    mean  median\n" + "\n".join(lines),
        family="monospace",
        fontsize=6.2,
        va="top",
    )
    axes[2, 3].axis("off")
    fig.suptitle("Photometric stereo on UW psm (courtesy S. Seitz): jaxrefl.ps", fontsize=11)
    fig.savefig(HERE / "ps_table.png", dpi=90, bbox_inches="tight")
    print(f"wrote {HERE / 'ps_table.png'}")


if __name__ == "__main__":
    main()
