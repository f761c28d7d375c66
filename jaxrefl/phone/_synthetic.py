"""Rendered phone photos of a sample in the printed frame, with known cameras (for the
tests and benchmarks).

A :class:`PhoneCamera` is a pinhole camera with radial distortion, OpenCV's model with
k1, k2 only: a point X (frame coordinates, cm, :mod:`jaxrefl.phone._frame`) goes to camera
coordinates x_c = R (X - C) (x right, y down, z forward), to a = x/z, b = y/z, and to
pixel (u, v) = (f a d + cx, f b d + cy) with d = 1 + k1 r^2 + k2 r^4, r^2 = a^2 + b^2.

:func:`render_photo` traces every sub-pixel (``supersample`` x ``supersample`` per pixel,
averaged: a box pixel) through the inverted distortion to the marker plane z = 0. The paper
(a square of side S + 3 cm with a square hole of side 13.2u where the sample shows
through) carries the tags, black reflectance 0.03 and white 0.8, Lambertian; through the
hole the ray goes on to the sample's plane z = -depth; beyond the paper lies a grey table.
Everything is lit by a point flash at the lens of power ``flash_power`` (radiance
L = P f_r cos(theta_i) / r^2, the flash-capture convention of :mod:`jaxrefl.demo`, no
vignetting). The sample is any BRDF of :mod:`jaxrefl.brdf` with parameter maps given as
a function of the position on the sample (:class:`SyntheticSample`), evaluated by
:func:`jaxrefl.scene.render`; :func:`render_sample` renders the same sample directly at
the pixel centres of a rectified N x N photo, the reference the rectification is compared
with. :func:`write_jpeg` encodes linear values as sRGB 8-bit JPEG with EXIF tags.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._frame import FrameLayout
from ._tags import tag_cells

__all__ = [
    "PhoneCamera",
    "SyntheticSample",
    "corner_pixels",
    "default_sample",
    "render_photo",
    "render_sample",
    "write_jpeg",
]

_BLACK, _WHITE, _TABLE = 0.03, 0.8, 0.15  # Lambertian reflectances of ink, paper, table
_PAGE_MARGIN = 1.5  # cm of paper beyond the tags' outer edges
_BUCKET = 1 << 16  # sample points are padded to a multiple of this (one compiled shape)
_HOLE = 13.2  # side of the hole in the paper, in layout units (the ring's inner edge: 14)


@dataclass(frozen=True)
class PhoneCamera:
    """A camera at ``position`` (frame coordinates, cm) looking at ``look_at``, turned by
    ``roll`` degrees about its axis; ``width`` x ``height`` pixels, focal length ``f`` and
    principal point (``cx``, ``cy``) in pixels, radial distortion ``k1``, ``k2``."""

    position: tuple[float, float, float]
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.0)
    roll: float = 0.0
    width: int = 640
    height: int = 480
    f: float = 520.0
    cx: float = 319.5
    cy: float = 239.5
    k1: float = 0.0
    k2: float = 0.0

    def rotation(self) -> np.ndarray:
        """R (world to camera): rows are the camera's x (right), y (down), z (forward)."""
        c = np.asarray(self.position, float)
        z = np.asarray(self.look_at, float) - c
        z /= np.linalg.norm(z)
        down = np.array([0.0, -1.0, 0.0])  # the page's bottom is the image's bottom
        y = down - (down @ z) * z
        y /= np.linalg.norm(y)
        x = np.cross(y, z)
        t = np.radians(self.roll)
        x, y = np.cos(t) * x + np.sin(t) * y, -np.sin(t) * x + np.cos(t) * y
        return np.stack([x, y, z])

    def camera_matrix(self) -> np.ndarray:
        return np.array([[self.f, 0, self.cx], [0, self.f, self.cy], [0, 0, 1.0]])

    def distortion(self) -> np.ndarray:
        """OpenCV's (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, 0.0, 0.0, 0.0])

    def project(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) frame points -> (..., 2) pixels."""
        xc = (np.asarray(points, float) - np.asarray(self.position)) @ self.rotation().T
        a, b = xc[..., 0] / xc[..., 2], xc[..., 1] / xc[..., 2]
        r2 = a * a + b * b
        d = 1 + self.k1 * r2 + self.k2 * r2 * r2
        return np.stack([self.f * a * d + self.cx, self.f * b * d + self.cy], -1)

    def rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unit directions (world) of the rays through pixels (u, v)."""
        ad, bd = (u - self.cx) / self.f, (v - self.cy) / self.f
        a, b = ad.copy(), bd.copy()
        for _ in range(50):  # fixed point of a d(a, b) = ad: contracts fast for |k r^2| << 1
            r2 = a * a + b * b
            d = 1 + self.k1 * r2 + self.k2 * r2 * r2
            a_new, b_new = ad / d, bd / d
            step = max(np.max(np.abs(a_new - a)), np.max(np.abs(b_new - b)))
            a, b = a_new, b_new
            if step < 1e-12:  # far below a pixel (1e-12 f ~ 1e-9 px)
                break
        dirs = np.stack([a, b, np.ones_like(a)], -1) @ self.rotation()
        return dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)


@dataclass(frozen=True)
class SyntheticSample:
    """A planar sample: a BRDF (``model``) and ``params_at(xy)``, its parameter maps at
    (..., 2) positions on the sample (cm, the sample's centre at 0)."""

    model: object
    params_at: Callable[[np.ndarray], dict[str, np.ndarray]]


def default_sample() -> SyntheticSample:
    """The demo's BRDF (GGX Cook–Torrance on Lambert, :mod:`jaxrefl.demo`) with smooth
    maps: albedo, F0 and roughness vary as sinusoids of periods 2.5-4 cm."""
    from jaxrefl.demo import demo_model

    model = demo_model()

    def params_at(xy: np.ndarray) -> dict[str, np.ndarray]:
        x, y = xy[..., 0], xy[..., 1]
        w = 2 * np.pi
        albedo = np.stack(
            [
                0.40 + 0.20 * np.sin(w * x / 3.0) * np.cos(w * y / 4.0),
                0.30 + 0.15 * np.cos(w * (x + y) / 3.5),
                0.20 + 0.10 * np.sin(w * y / 2.5 + 1.0),
            ],
            -1,
        )
        f0 = 0.05 + 0.02 * np.sin(w * (x - y) / 4.0)
        rough = 0.55 + 0.12 * np.cos(w * x / 4.0) * np.sin(w * y / 3.0 + 0.5)
        return {
            "albedo": albedo,
            "specular": np.repeat(f0[..., None], 3, -1),
            "alpha": rough**2,
        }

    return SyntheticSample(model=model, params_at=params_at)


def _radiance(sample: SyntheticSample, points: np.ndarray, flash: np.ndarray, power: float):
    """(n, 3) radiance of the sample at (n, 3) points on its plane (its own z = 0)."""
    import jax.numpy as jnp

    from jaxrefl.scene import PinholeCamera, PointLight, render

    n = len(points)
    pad = -n % _BUCKET  # one compiled program for every photo's number of sample points
    points = np.concatenate([points, np.zeros((pad, 3))]) if pad else points
    f32 = jnp.float32  # a photo's radiance needs no more; float64 would double the cost
    params = {k: jnp.asarray(v, f32) for k, v in sample.params_at(points[:, :2]).items()}
    img = render(
        sample.model,  # type: ignore[arg-type]
        params,
        PointLight(jnp.asarray(flash, f32), jnp.full((3,), power, f32)),
        PinholeCamera(jnp.asarray(flash, f32), look_at=(0.0, 0.0, 0.0)),
        points=jnp.asarray(points, f32),
        cos4=False,
    )
    return np.asarray(img[0], np.float64)[:n]


def _paper(layout: FrameLayout, xy: np.ndarray) -> np.ndarray:
    """Reflectance of the marker plane at (n, 2) positions; NaN in the hole."""
    u = layout.unit
    x, y = xy[:, 0], xy[:, 1]
    edge = layout.side / 2 + _PAGE_MARGIN
    rho = np.where((np.abs(x) <= edge) & (np.abs(y) <= edge), _WHITE, _TABLE)
    rho[(np.abs(x) < _HOLE / 2 * u) & (np.abs(y) < _HOLE / 2 * u)] = np.nan
    half = layout.tag_size / 2
    for tag_id, (tx, ty) in enumerate(layout.centers()):
        col = np.floor((x - (tx - half)) / layout.tag_size * 8).astype(int)
        row = np.floor(((ty + half) - y) / layout.tag_size * 8).astype(int)
        inside = (col >= 0) & (col < 8) & (row >= 0) & (row < 8)
        cells = tag_cells(tag_id)
        rho[inside] = np.where(cells[row[inside], col[inside]], _WHITE, _BLACK)
    return rho


def render_photo(
    camera: PhoneCamera,
    layout: FrameLayout,
    sample: SyntheticSample,
    *,
    depth: float = 0.0,
    flash_power: float = 1500.0,
    supersample: int = 3,
) -> np.ndarray:
    """(H, W, 3) linear radiance seen by ``camera`` (module docstring)."""
    n = supersample
    off = (np.arange(n) + 0.5) / n - 0.5
    v, u = np.mgrid[: camera.height, : camera.width].astype(float)
    shape = (camera.height, camera.width, n, n)
    u = np.broadcast_to(u[..., None, None] + off[None, None, None, :], shape).ravel()
    v = np.broadcast_to(v[..., None, None] + off[None, None, :, None], shape).ravel()
    c = np.asarray(camera.position, float)
    d = camera.rays(u, v)
    hit0 = c + (-c[2] / d[:, 2])[:, None] * d
    rho = _paper(layout, hit0[:, :2])
    out = np.zeros((u.size, 3))
    paper = ~np.isnan(rho)
    r2 = np.sum((c - hit0[paper]) ** 2, -1)
    cos_i = (c[2] - hit0[paper, 2]) / np.sqrt(r2)
    out[paper] = (rho[paper] / np.pi * flash_power * cos_i / r2)[:, None]
    hole = ~paper
    hit = c + ((-depth - c[2]) / d[hole, 2])[:, None] * d[hole]
    on_sample = hit - np.array([0.0, 0.0, -depth])  # the sample's own frame: its surface z = 0
    out[hole] = _radiance(sample, on_sample, c + np.array([0.0, 0.0, depth]), flash_power)
    return out.reshape(camera.height, camera.width, n * n, 3).mean(2)


def render_sample(
    position: np.ndarray,
    layout: FrameLayout,
    sample: SyntheticSample,
    size: int,
    *,
    depth: float = 0.0,
    flash_power: float = 1500.0,
) -> np.ndarray:
    """(size, size, 3) radiance at the pixel centres of the rectified sample square, seen
    and lit from ``position`` (frame coordinates)."""
    from jaxrefl.scene import planar_points

    pts = np.asarray(planar_points(size, size, layout.sample_side), np.float64)
    flash = np.asarray(position, float) + np.array([0.0, 0.0, depth])
    return _radiance(sample, pts.reshape(-1, 3), flash, flash_power).reshape(size, size, 3)


def corner_pixels(camera: PhoneCamera, layout: FrameLayout) -> np.ndarray:
    """(16, 4, 2) true pixel positions of the tags' corners (layout order)."""
    return camera.project(layout.corners())


def write_jpeg(
    path: str | Path, linear: np.ndarray, exif: dict[int, object] | None = None, quality=95
) -> Path:
    """Encode (H, W, 3) linear values as sRGB 8-bit (clipped) and write a JPEG (4:4:4) with
    ``exif``: {tag: value}; tags of the Exif sub-IFD (0x8769: exposure, ISO, aperture, ...)
    are placed there, the others (Orientation, Make, Model) in IFD0."""
    from PIL import Image

    from jaxrefl.scene import SRGBResponse

    enc = np.asarray(SRGBResponse().apply(np.asarray(linear, np.float64)))
    img = Image.fromarray(np.rint(np.clip(enc, 0, 1) * 255).astype(np.uint8))
    ex = Image.Exif()
    for tag, value in (exif or {}).items():
        if tag in _IFD0_TAGS:
            ex[tag] = value
        else:
            ex.get_ifd(0x8769)[tag] = value
    path = Path(path)
    img.save(path, quality=quality, subsampling=0, exif=ex.tobytes())
    return path


_IFD0_TAGS = {0x010F, 0x0110, 0x0112}  # Make, Model, Orientation
