"""Writing a capture in the generic layout (``capture.json`` beside its photos), which
:func:`~jaxrefl.io.load_capture` reads back (:mod:`._capture_layouts`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from jaxrefl._errors import JaxreflError

from ._photos import response_for, write_png, x64

__all__ = ["save_generic_capture"]


def save_generic_capture(
    folder: str | Path,
    images,
    *,
    side: float,
    light_power,
    camera_pos,
    light_pos=None,
    light_dir=None,
    transfer: Any = "linear",
    file_format: str | None = None,
    unit: str = "cm",
    mask=None,
    saturation: float | None = None,
) -> Path:
    """Write linear images and their geometry in the generic layout; returns capture.json.

    ``images`` (K, H, W, C) linear values. ``file_format``: ``"exr"`` (float32; default
    for ``transfer="linear"``), ``"png16"`` (default otherwise) or ``"png8"``: PNG values
    are ``round(curve(x) * top)`` with the transfer's curve, clipped to [0, 1].
    ``light_pos`` (K, 3) point lights or ``light_dir`` (K, 3) directional ones;
    ``light_power`` broadcastable to (K, C); ``camera_pos`` (K, 3) or (3,) (one camera);
    ``mask`` (H, W) bool, True = keep.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    img = np.asarray(images, np.float64)
    if img.ndim != 4:
        raise JaxreflError(f"images must be (K, H, W, C), got {img.shape}")
    k, h, w, c = img.shape
    if (light_pos is None) == (light_dir is None):
        raise JaxreflError("give exactly one of light_pos and light_dir")
    geo = np.broadcast_to(np.asarray(light_pos if light_dir is None else light_dir, float), (k, 3))
    power = np.asarray(light_power, float)
    if power.ndim == 1 and power.size == k and k != c:  # one value per photo
        power = power[:, None]
    power = np.broadcast_to(power, (k, c))
    cams = np.broadcast_to(np.asarray(camera_pos, float), (k, 3))
    response, _ = response_for(transfer, folder / "capture.json")
    fmt = file_format or ("exr" if str(transfer) == "linear" else "png16")
    names = []
    for i in range(k):
        if fmt == "exr":
            from ._exr import write_exr, write_exr_rgb

            name = f"{i:02d}.exr"
            if c == 3:
                write_exr_rgb(folder / name, img[i].astype(np.float32))
            elif c == 1:
                write_exr(folder / name, {"Y": img[i, ..., 0].astype(np.float32)})
            else:
                raise JaxreflError(f"EXR photos need 1 or 3 channels, got {c}")
        elif fmt in ("png8", "png16"):
            import jax.numpy as jnp

            if not np.all(np.isfinite(img[i])):
                raise JaxreflError(f"photo {i} holds NaN/Inf, which a PNG cannot store")
            top = 255 if fmt == "png8" else 65535
            with x64():
                enc = np.asarray(response.apply(jnp.asarray(img[i], jnp.float64)))
            q = np.rint(np.clip(enc, 0.0, 1.0) * top).astype(np.uint8 if top == 255 else np.uint16)
            name = f"{i:02d}.png"
            write_png(folder / name, q)
        else:
            raise JaxreflError(f"file_format must be 'exr', 'png8' or 'png16', got {file_format!r}")
        names.append(name)
    if light_dir is None:
        lights = [
            {"type": "point", "position": p.tolist(), "power": e.tolist()}
            for p, e in zip(geo, power, strict=True)
        ]
    else:
        lights = [
            {"type": "directional", "direction": d.tolist(), "irradiance": e.tolist()}
            for d, e in zip(geo, power, strict=True)
        ]
    spec: dict[str, Any] = {
        "images": names,
        "transfer": transfer,
        "side": float(side),
        "unit": unit,
        "lights": lights,
        "cameras": [{"position": p.tolist()} for p in cams],
    }
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != (h, w):
            raise JaxreflError(f"mask must be (H, W) = ({h}, {w}), got {m.shape}")
        write_png(folder / "mask.png", m.astype(np.uint8) * 255)
        spec["mask"] = "mask.png"
    if saturation is not None:
        spec["saturation"] = float(saturation)
    out = folder / "capture.json"
    out.write_text(json.dumps(spec, indent=2))
    return out
