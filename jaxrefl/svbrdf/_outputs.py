"""Files of a capture fit: ``maps.exr``, ``report.json`` and PNG previews.

``maps.exr`` (single part, float32 and uint32 channels, ZIP): every map of
:class:`~jaxrefl.svbrdf.CaptureFit` as a ``<layer>.<channel>`` channel (``albedo.R``,
``specular.Y``, ``roughness.Y``, ``roughness_std.Y``, ``corr_albedo_R_alpha.Y``,
``status.Y``, ...; the table in :mod:`jaxrefl.io._channels`, which Mitsuba 3's
``Bitmap(...).split()`` and OpenEXR layer readers split into RGB and Y images), with
metadata ``jaxrefl/model``, ``jaxrefl/units``, ``jaxrefl/correlations`` (layer -> the two
parameter labels), ``jaxrefl/status_codes``, ``jaxrefl/laplace_flags``,
``jaxrefl/model_checks`` (the bits of the ``misspecified`` map,
:mod:`jaxrefl.svbrdf._check`) and ``jaxrefl/version``. Writes are atomic
(:func:`jaxrefl.io.write_exr`).

Previews (8-bit PNG, at most ``preview_side`` pixels a side, strided):
``params.png`` (albedo, specular, roughness with colour bars in their units, and the fit
status with a legend of the codes present), ``uncertainty.png`` (std maps on log colour
scales from their 1st to 99th percentile, colour bars in the maps' units, and the Laplace
flag with a legend), ``compare.png`` (photographed against fitted, linear radiance shown
with the capture's gamma, for up to three photos, held-out ones first) and, when photos
were held out, ``heldout.png`` (per-pixel RMSE over the held-out photos' valid
observations, linear radiance).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxrefl import fit
from jaxrefl._jsonsafe import report_json
from jaxrefl.io import write_text_atomic

from ._check import ModelCheck
from ._data import pixel_block
from ._job_types import CaptureFit
from ._maps import status_meanings
from ._models import CAPTURE_MODELS

__all__ = ["predict_photos", "write_outputs"]


def write_maps(result: CaptureFit, path: Path) -> Path:
    """The maps as one EXR file (module docstring)."""
    from jaxrefl.io import corr_name, exr_channels, write_exr

    meta = {
        "model": result.job.model,
        "model_description": CAPTURE_MODELS[result.job.model],
        "parameters": list(result.labels),
        "units": {
            "albedo": "diffuse albedo, 1 (f_r = albedo/pi)",
            "specular": "Schlick F0, 1",
            "alpha": "GGX/Beckmann width alpha (not perceptual)",
            "roughness": "perceptual roughness sqrt(alpha)",
            "tilt_x, tilt_y": "slopes of the shading normal, 1 (ggx_normal)",
            "normal": "unit shading normal in the sample frame (+z = the sample's normal)",
            "base_color, metallic": "the metallic-roughness view of a coloured F0 (glTF 2.0; "
            "jaxrefl.brdf.specular_to_metallic), 1",
            "*_std": "Laplace standard deviation, same units",
            "corr_*": "Laplace correlation of two parameters (jaxrefl/correlations), 1",
            "noise_std": "estimated noise std, radiance units of the capture",
        },
        "correlations": {
            corr_name(a, b): [a, b]
            for i, a in enumerate(result.labels)
            for b in result.labels[i + 1 :]
        },
        "status_codes": status_meanings(),
        "laplace_flags": {b.name: int(b.value) for b in fit.LaplaceFlag},
        # the misspecified map's bits: pixels whose intervals are not calibrated
        "model_checks": {b.name: int(b.value) for b in ModelCheck},
    }
    if result.pooled is not None:
        meta["pooled"] = result.pooled.as_dict()
    return write_exr(path, exr_channels(result.maps), metadata=meta)


def _strided(capture, step: int):
    if step == 1:
        return capture
    return replace(
        capture,
        images=capture.images[:, ::step, ::step],
        status=capture.status[:, ::step, ::step],
        points=capture.points[::step, ::step],
    )


def predict_photos(result: CaptureFit, capture, photos, step: int = 1) -> tuple[Any, Any]:
    """(photographed, fitted) linear radiance (len(photos), H/step, W/step, C); the fitted
    under the light the fit used (``result.light``: its estimate of the flash, as the report's
    held-out errors are)."""
    lit = capture if result.light is None else result.light.apply(capture)
    sub = _strided(lit.select(list(photos)), step)
    k, h, w, c = sub.shape
    model, space = result.model()
    theta = result.theta.reshape(*result.maps["status"].shape, -1)[::step, ::step]
    theta = theta.reshape(h * w, -1)
    ok = np.all(np.isfinite(theta), axis=-1)
    data = pixel_block(sub, 0, h * w)
    res = fit.make_residual(model, space)
    import jax

    pred = jax.jit(jax.vmap(res.predict))(jnp.asarray(np.where(ok[:, None], theta, 0.0)), data)
    pred = np.where(ok[:, None, None], np.asarray(pred), np.nan)
    pred = np.moveaxis(pred.reshape(h, w, k, c), 2, 0)
    return sub.images, pred


def _encode(x: np.ndarray, gamma: float = 2.2) -> np.ndarray:
    return np.clip(np.nan_to_num(x, nan=0.0), 0.0, 1.0) ** (1.0 / gamma)


# Units of the std maps in the previews (the maps' own units: module docstring of write_maps).
_STD_UNITS = {
    "albedo_std.G": "diffuse albedo (green), 1",
    "specular_std": "specular F0, 1",
    "roughness_std": "perceptual roughness, 1",
}


def _categorical(fig, ax, codes: np.ndarray, names: dict[int, str], title: str) -> None:
    """A map of integer codes with a legend of the codes present (name and count)."""
    import matplotlib.colors as mcolors
    from matplotlib.patches import Patch

    present = [int(v) for v in np.unique(codes)]
    palette = [mcolors.to_rgba(f"C{i % 10}") for i in range(len(present))]
    index = np.searchsorted(present, codes)
    ax.imshow(np.asarray(palette)[index], interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.axis("off")
    handles = [
        Patch(color=palette[i], label=f"{v} {names.get(v, '?')} ({int(np.sum(codes == v))})")
        for i, v in enumerate(present)
    ]
    ax.legend(
        handles=handles,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.02),
        fontsize=7,
        frameon=False,
        ncol=1,
    )


def _flag_name(value: int) -> str:
    if value == 0:
        return "reliable"
    return "|".join(b.name or str(b.value) for b in fit.LaplaceFlag if value & b.value)


def _log_std(fig, ax, v: np.ndarray, title: str, units: str) -> None:
    """A std map on a log colour scale (1st to 99th percentile of the positive values), its
    colour bar labelled in the map's units."""
    from matplotlib.colors import LogNorm

    pos = v[np.isfinite(v) & (v > 0)]
    lo, hi = np.percentile(pos, [1, 99]) if pos.size else (1e-3, 1.0)
    hi = max(hi, lo * 10.0)  # at least a decade, so that a uniform map still has a scale
    import matplotlib

    cmap = matplotlib.colormaps["magma"].with_extremes(bad="0.6")  # grey: no std there
    im = ax.imshow(np.where(v > 0, v, np.nan), cmap=cmap, norm=LogNorm(vmin=lo, vmax=hi))
    ax.set_title(f"{title} (grey: none)", fontsize=9)
    ax.axis("off")
    fig.colorbar(im, ax=ax, fraction=0.046).set_label(f"std ({units}), log scale", fontsize=7)


def write_previews(result: CaptureFit, capture, out: Path, preview_side: int = 384) -> list[Path]:
    """PNG previews (module docstring): parameter maps, std maps on log colour scales with
    colour bars in their units, status and Laplace-flag maps with legends, photographed
    against fitted photos, and with held-out photos the map of their per-pixel RMSE."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    h, w = result.maps["status"].shape
    step = max(1, -(-max(h, w) // preview_side))
    m = {k: v[::step, ::step] for k, v in result.maps.items()}
    paths = []

    def show(ax, img, title, **kw):
        im = ax.imshow(img, **kw)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        return im

    def show_bar(fig, ax, img, title, label, **kw):
        fig.colorbar(show(ax, img, title, **kw), ax=ax, fraction=0.046).set_label(label, fontsize=7)

    def save(fig, name):
        fig.tight_layout()
        paths.append(out / name)
        fig.savefig(paths[-1], dpi=100, bbox_inches="tight")
        plt.close(fig)

    # Parameter maps.
    names = [n for n in ("specular", "roughness") if n in m]
    rgb = [n for n in ("albedo", "specular") if f"{n}.R" in m]  # coloured maps
    n_ax = max(1, len(rgb)) + len(names) + 1
    fig, axes = plt.subplots(1, n_ax, figsize=(3.2 * n_ax, 4.2))
    titles = {"albedo": "diffuse albedo (gamma 2.2)", "specular": "specular F0 (gamma 2.2)"}
    for ax, n in zip(axes, rgb, strict=False):
        show(ax, _encode(np.stack([m[f"{n}.{c}"] for c in "RGB"], -1)), titles[n])
    units = {"specular": "Schlick F0, 1", "roughness": "perceptual roughness, 1"}
    for ax, n in zip(axes[max(1, len(rgb)) :], names, strict=False):
        show_bar(fig, ax, m[n], n, units[n], cmap="viridis")
    status_names = {int(s): s.name or str(int(s)) for s in fit.Status}
    _categorical(fig, axes[-1], np.asarray(m["status"], np.int64), status_names, "fit status")
    save(fig, "params.png")

    # Uncertainty maps.
    std_names = [n for n in _STD_UNITS if n in m]
    fig, axes = plt.subplots(1, len(std_names) + 1, figsize=(3.4 * (len(std_names) + 1), 4.2))
    axes = np.atleast_1d(axes)
    for ax, sn in zip(axes, std_names, strict=False):
        _log_std(fig, ax, np.asarray(m[sn], np.float64), sn, _STD_UNITS[sn])
    flags = np.asarray(m["laplace_flag"], np.int64)
    flag_names = {int(v): _flag_name(int(v)) for v in np.unique(flags)}
    _categorical(fig, axes[-1], flags, flag_names, "Laplace flag")
    save(fig, "uncertainty.png")

    # Photographed against fitted.
    k = capture.n_photos
    held = list(result.job.holdout)
    photos = held + [i for i in range(k) if i not in held]
    photos = photos[:3]
    shot, pred = predict_photos(result, capture, photos, step)
    fig, axes = plt.subplots(len(photos), 2, figsize=(6.4, 3.2 * len(photos)), squeeze=False)
    for row, i in enumerate(photos):
        tag = " (held out)" if i in held else ""
        show(axes[row, 0], _encode(shot[row]), f"photo {i}{tag}")
        show(axes[row, 1], _encode(pred[row]), f"fitted {i}")
    save(fig, "compare.png")

    # Held-out error per pixel: RMSE over the held-out photos' valid observations.
    if held:
        sub = _strided(capture.select(held), step)
        _, pred_h = predict_photos(result, capture, held, step)
        err = np.where(np.asarray(sub.status) == 0, np.asarray(sub.images) - pred_h, np.nan)
        with np.errstate(invalid="ignore"):
            rmse = np.sqrt(np.nanmean(err**2, axis=(0, 3)))
        fig, ax = plt.subplots(1, 1, figsize=(4.4, 4.0))
        finite = rmse[np.isfinite(rmse)]
        hi = float(np.percentile(finite, 99)) if finite.size else 1.0
        show_bar(
            fig,
            ax,
            rmse,
            f"held-out RMSE per pixel (photos {', '.join(map(str, held))})",
            "linear radiance of the capture",
            cmap="inferno",
            vmin=0.0,
            vmax=hi,
        )
        save(fig, "heldout.png")
    return paths


def write_outputs(result: CaptureFit, capture, out_dir: str | Path, previews: bool = True) -> dict:
    """Write maps.exr, report.json and (optionally) the previews; return the file list."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Any] = {"maps": str(write_maps(result, out / "maps.exr"))}
    if previews:
        files["previews"] = [str(p) for p in write_previews(result, capture, out)]
    report = dict(result.report)
    report["files"] = files
    write_text_atomic(out / "report.json", report_json(report, default=_json_default))
    files["report"] = str(out / "report.json")
    return files


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
