"""Files of a capture fit: ``maps.exr``, ``report.json`` and PNG previews.

``maps.exr`` (single part, float32 and uint32 channels, ZIP): every map of
:class:`~jaxrefl.svbrdf.CaptureFit` as a ``<layer>.<channel>`` channel (``albedo.R``,
``specular.Y``, ``roughness.Y``, ``roughness_std.Y``, ``corr_albedo_R_alpha.Y``,
``status.Y``, ...; the table in :mod:`jaxrefl.io._channels`, which Mitsuba 3's
``Bitmap(...).split()`` and OpenEXR layer readers split into RGB and Y images), with
metadata ``jaxrefl/model``, ``jaxrefl/units``, ``jaxrefl/correlations`` (layer -> the two
parameter labels), ``jaxrefl/status_codes``, ``jaxrefl/laplace_flags`` and
``jaxrefl/version``. Writes are atomic (:func:`jaxrefl.io.write_exr`).

Previews (8-bit PNG, at most ``preview_side`` pixels a side, strided):
``params.png`` (albedo, specular, roughness, status), ``uncertainty.png`` (std maps and
the Laplace flag), ``compare.png`` (photographed against fitted, linear radiance shown with
the capture's gamma, for up to three photos, held-out ones first).
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxrefl import fit
from jaxrefl._jsonsafe import report_json

from ._data import pixel_block
from ._job import CaptureFit, status_meanings
from ._models import CAPTURE_MODELS

__all__ = ["predict_photos", "write_outputs"]


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


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
    }
    if result.extra.get("pooled") is not None:
        meta["pooled"] = result.extra["pooled"].as_dict()
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
    """(photographed, fitted) linear radiance (len(photos), H/step, W/step, C)."""
    sub = _strided(capture.select(list(photos)), step)
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


def write_previews(result: CaptureFit, capture, out: Path, preview_side: int = 384) -> list[Path]:
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

    def show_bar(fig, ax, img, title, **kw):
        fig.colorbar(show(ax, img, title, **kw), ax=ax, fraction=0.046)

    def save(fig, name):
        fig.tight_layout()
        paths.append(out / name)
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)

    # Parameter maps.
    names = [n for n in ("specular", "roughness") if n in m]
    rgb = [n for n in ("albedo", "specular") if f"{n}.R" in m]  # coloured maps
    n_ax = max(1, len(rgb)) + len(names) + 1
    fig, axes = plt.subplots(1, n_ax, figsize=(3.2 * n_ax, 3.4))
    titles = {"albedo": "diffuse albedo (gamma 2.2)", "specular": "specular F0 (gamma 2.2)"}
    for ax, n in zip(axes, rgb, strict=False):
        show(ax, _encode(np.stack([m[f"{n}.{c}"] for c in "RGB"], -1)), titles[n])
    for ax, n in zip(axes[max(1, len(rgb)) :], names, strict=False):
        show_bar(fig, ax, m[n], n, cmap="viridis")
    show_bar(fig, axes[-1], m["status"], "fit status", cmap="tab10", vmin=0, vmax=9)
    save(fig, "params.png")

    # Uncertainty maps.
    std_names = [n for n in ("albedo_std.G", "specular_std", "roughness_std") if n in m]
    fig, axes = plt.subplots(1, len(std_names) + 1, figsize=(3.2 * (len(std_names) + 1), 3.4))
    axes = np.atleast_1d(axes)
    for ax, sn in zip(axes, std_names, strict=False):
        v = m[sn]
        hi = np.nanpercentile(v, 99) if np.any(np.isfinite(v)) else 1.0
        show_bar(fig, ax, v, sn, cmap="magma", vmin=0, vmax=hi)
    show_bar(fig, axes[-1], m["laplace_flag"], "Laplace flag (0 = reliable)", cmap="tab20")
    save(fig, "uncertainty.png")

    # Photographed against fitted.
    k = capture.n_photos
    photos = list(result.job.holdout) + [i for i in range(k) if i not in result.job.holdout]
    photos = photos[:3]
    shot, pred = predict_photos(result, capture, photos, step)
    fig, axes = plt.subplots(len(photos), 2, figsize=(6.4, 3.2 * len(photos)), squeeze=False)
    for row, i in enumerate(photos):
        tag = " (held out)" if i in result.job.holdout else ""
        show(axes[row, 0], _encode(shot[row]), f"photo {i}{tag}")
        show(axes[row, 1], _encode(pred[row]), f"fitted {i}")
    save(fig, "compare.png")
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
    _atomic_text(out / "report.json", report_json(report, default=_json_default))
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
