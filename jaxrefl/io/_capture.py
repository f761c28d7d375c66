"""Planar SVBRDF captures under a near light: photos, per-observation status and geometry.

A :class:`Capture` holds K photos of a flat sample, each taken under one light (a phone
flash close to the sample: a point light; or a distant, directional one) from one camera
position, as read by :func:`jaxrefl.io.load_capture` from one of three layouts
(:mod:`jaxrefl.io._capture_layouts`: svbrdf-diff-renderer, MaterialGAN, generic).

Convention (MaterialGAN, Guo et al. 2020, and its public captures): the sample is the
square of side S centred at the origin of the plane z = 0, +z its normal, and pixel
(row i, column j) of an H x W photo lies at

    x = ((j + 0.5)/W - 0.5) S,     y = -((i + 0.5)/H - 0.5) S,     z = 0

(:func:`jaxrefl.scene.planar_points`). Light and camera positions are in the same frame and
unit (cm in both public layouts). The photos record, per channel,

    L_k(x) = f_r(wi, wo) * E_k(x) * cos(theta_i),   E_k(x) = I_k / r_k(x)^2 (point light)
                                                    E_k(x) = E_k           (directional)

with wi, wo unit vectors from x towards the light and the camera (the local frame of a
planar sample is the world frame: normal +z, tangent +x) and I_k the light's intensity
(``light_power``). :meth:`Capture.per_pixel_geometry` returns wi, wo, E and cos(theta_i)
so that ``model.eval(params, wi, wo) * irradiance * cos_i[..., None]`` is the prediction
of every observation; it agrees with :func:`jaxrefl.scene.render` with ``cos4=False``.

Observation status
------------------
``status`` (K, H, W, C) uint8 tells, per photo, pixel and channel, how an observation may
be used (:class:`ObsStatus`; failures are values, not exceptions):

====  ====================  ===========================================================
code  name                  meaning
====  ====================  ===========================================================
0     ok                    a measurement: use the value
1     saturated             clipped at the top code of an integer image (or at the
                            generic layout's ``saturation`` level): censored, the true
                            value is >= ``saturation_level`` (the lowest linear value
                            that rounds to the top code; the recorded value is above it)
2     dark                  0 in an integer file: censored, true value <= ``dark_level``
                            (half a quantisation step, linearised)
3     nonfinite             NaN or Inf in a float (EXR) image; the value is set to 0
4     negative              a negative value in a float image (kept as recorded)
5     masked                excluded by a user mask or a zero alpha
6     light_below_horizon   the light is at or below the sample plane at this pixel
                            (geometry stays finite; cos_i = 0 there). A file with such a
                            light is refused (:mod:`jaxrefl.io._capture_checks`); a
                            capture built in Python may hold one
7     view_below_horizon    the camera is at or below the sample plane at this pixel (as 6)
8     censored_mixed        after :meth:`Capture.downsample`: the block mixes saturated
                            and dark observations, so its mean bounds nothing
====  ====================  ===========================================================

When several apply, the order of precedence is 3, 4, 5, 6, 7, then 8, 1, 2.
:attr:`Capture.valid` is ``status == 0``; :attr:`Capture.censored_high` and
:attr:`Capture.censored_low` select codes 1 and 2.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from jaxrefl._errors import JaxreflError

__all__ = ["OBS_STATUS", "Capture", "CaptureError", "ObsStatus", "geometry_status", "obs_severity"]


class CaptureError(JaxreflError):
    """A capture folder or file is missing, malformed or inconsistent.

    The message names the file, the field (a JSON key, a text file's line) and the problem.
    """

    def __init__(self, path: str | Path | None, problem: str, field: str | None = None):
        self.path = None if path is None else Path(path)
        self.field = field
        self.problem = problem
        where = "" if field is None else f": {field}"
        super().__init__(f"{path}{where}: {problem}")


class ObsStatus(enum.IntEnum):
    """Per-observation status codes (module docstring for their meanings)."""

    OK = 0
    SATURATED = 1
    DARK = 2
    NONFINITE = 3
    NEGATIVE = 4
    MASKED = 5
    LIGHT_BELOW_HORIZON = 6
    VIEW_BELOW_HORIZON = 7
    CENSORED_MIXED = 8


#: code -> readable name of every :class:`ObsStatus`.
OBS_STATUS: dict[int, str] = {int(s): s.name.lower() for s in ObsStatus}

# Codes from least to most severe (module docstring): the most severe one present wins.
# Severity does not follow the numbers, which are stored and never change.
_PRECEDENCE = (
    ObsStatus.OK,
    ObsStatus.DARK,
    ObsStatus.SATURATED,
    ObsStatus.CENSORED_MIXED,
    ObsStatus.VIEW_BELOW_HORIZON,
    ObsStatus.LIGHT_BELOW_HORIZON,
    ObsStatus.MASKED,
    ObsStatus.NEGATIVE,
    ObsStatus.NONFINITE,
)
_BY_RANK = np.array(_PRECEDENCE, np.uint8)  # rank -> code
_RANK = np.zeros(256, np.uint8)  # code -> rank
_RANK[_BY_RANK] = np.arange(len(_PRECEDENCE))


def obs_severity(status: npt.ArrayLike) -> np.ndarray:
    """The precedence rank of each :class:`ObsStatus` code (uint8): 0 for ``ok`` up to 8 for
    ``nonfinite``, in the order of the module docstring (not the numeric order of the codes)."""
    return _RANK[np.asarray(status, np.uint8)]


def _unit_or_z(d: np.ndarray) -> np.ndarray:
    """d/|d| along the last axis; a zero vector maps to +z (as ``safe_normalize``)."""
    r2 = np.sum(d * d, axis=-1, keepdims=True)
    ok = r2 > 0
    # A zero-length vector (the light on the point itself) has no direction; +z is valid.
    d_safe = np.where(ok, d, np.array([0.0, 0.0, 1.0]))
    return d_safe / np.sqrt(np.where(ok, r2, 1.0))


def geometry_status(
    status: np.ndarray,
    points: np.ndarray,
    light_pos: np.ndarray | None,
    light_dir: np.ndarray | None,
    camera_pos: np.ndarray,
) -> np.ndarray:
    """``status`` with codes 6/7 set where the light/camera is at or below the plane.

    A point light k is below the horizon of point x when ``light_pos[k].z <= x.z`` (the
    sample's normal is +z); a directional light when its direction has z <= 0.
    """
    out = status.copy()
    z = points[..., 2]
    for k in range(status.shape[0]):
        if light_pos is not None:
            lz = light_pos[k, 2] - z
        elif light_dir is not None:
            lz = light_dir[k, 2]
        else:
            raise JaxreflError("geometry_status needs light_pos or light_dir")
        below_l = np.broadcast_to(np.asarray(lz) <= 0.0, z.shape)
        below_v = camera_pos[k, 2] - z <= 0.0
        for code, below in (
            (ObsStatus.VIEW_BELOW_HORIZON, below_v),
            (ObsStatus.LIGHT_BELOW_HORIZON, below_l),
        ):
            if np.any(below):
                sk = out[k]
                # masked and invalid values (more severe) stay
                keep = obs_severity(sk[below]) >= _RANK[ObsStatus.MASKED]
                sk[below] = np.where(keep, sk[below], code)
    return out


@dataclass(frozen=True, eq=False)
class Capture:
    """K photos of a planar sample with their lights, cameras and per-observation status.

    Attributes
    ----------
    images:
        (K, H, W, C) float32 linear radiance in the capture's units (photos linearised with
        the layout's ``transfer``; non-finite values replaced by 0, see ``status``).
    status:
        (K, H, W, C) uint8 :class:`ObsStatus` codes.
    light_pos, light_dir:
        (K, 3) float64 point-light positions or directional-light unit directions (from the
        sample towards the light); exactly one is not None.
    light_power:
        (K, C) float64 intensity of point lights (irradiance = power/r^2) or irradiance of
        directional lights.
    camera_pos:
        (K, 3) float64 camera positions.
    side:
        S, the side of the imaged square, in ``unit``.
    points:
        (H, W, 3) float64 pixel positions on the sample plane (module docstring).
    layout, source, files, transfer, bit_depth, unit:
        where it came from: the layout name, the folder or file read, the K photo files in
        order, the transfer curve (``"gamma2.2"``, ``"srgb"``, ``"linear"``,
        ``"tabulated"``), the bits per sample of the files (8/16 integer; 16/32 float) and
        the length unit.
    dark_level, saturation_level:
        linear bounds of the censored observations (codes 2 and 1).
    meta:
        anything else the layout said (e.g. photo indices, co-located flash).
    """

    images: np.ndarray
    status: np.ndarray
    light_pos: np.ndarray | None
    light_dir: np.ndarray | None
    light_power: np.ndarray
    camera_pos: np.ndarray
    side: float
    points: np.ndarray
    layout: str = "generic"
    source: Path | None = None
    files: list[Path] = field(default_factory=list)
    transfer: str = "linear"
    bit_depth: int = 32
    unit: str = "cm"
    dark_level: float = 0.0
    saturation_level: float = float("inf")
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        images = np.asarray(self.images, dtype=np.float32)
        status = np.asarray(self.status, dtype=np.uint8)
        if images.ndim != 4 or status.shape != images.shape:
            raise JaxreflError(
                f"images must be (K, H, W, C) and status the same shape, got {images.shape} "
                f"and {status.shape}"
            )
        k, h, w, c = images.shape
        if k < 1:
            raise CaptureError(self.source, "holds no photo; give at least one", "images")
        if (self.light_pos is None) == (self.light_dir is None):
            raise JaxreflError("give exactly one of light_pos (point) and light_dir (directional)")
        lp = None if self.light_pos is None else np.asarray(self.light_pos, np.float64)
        ld = None if self.light_dir is None else np.asarray(self.light_dir, np.float64)
        cp = np.asarray(self.camera_pos, np.float64)
        pw = np.asarray(self.light_power, np.float64)
        try:  # a number, one per channel (C,), one per photo (K, 1), or (K, C)
            pw = np.broadcast_to(pw, (k, c))
        except ValueError:
            raise JaxreflError(
                f"light_power of shape {pw.shape} does not broadcast to (K, C) = ({k}, {c}); "
                "give one value per photo as shape (K, 1)"
            ) from None
        pts = np.asarray(self.points, np.float64)
        for name, a, shape in (
            ("light_pos", lp, (k, 3)),
            ("light_dir", ld, (k, 3)),
            ("camera_pos", cp, (k, 3)),
            ("points", pts, (h, w, 3)),
        ):
            if a is not None and a.shape != shape:
                raise JaxreflError(f"{name} must have shape {shape}, got {a.shape}")
        # Geometry must be finite: a NaN direction or position has no safe fallback, and a
        # light direction must have a length to be normalised.
        for name, a in (
            ("light_pos", lp),
            ("light_dir", ld),
            ("camera_pos", cp),
            ("light_power", pw),
            ("points", pts),
            ("side", np.asarray(self.side, np.float64)),
        ):
            if a is not None and not np.all(np.isfinite(a)):
                idx = np.argwhere(~np.isfinite(np.atleast_1d(a)))[0]
                raise CaptureError(
                    self.source,
                    f"holds a non-finite value at index {tuple(int(i) for i in idx)}; "
                    "geometry and light power must be finite numbers",
                    name,
                )
        for name, a in (("light_pos", lp), ("camera_pos", cp), ("points", pts)):
            # A distance whose square overflows has no direction or irradiance in float64.
            with np.errstate(over="ignore"):
                far = None if a is None else ~np.isfinite(np.sum(a * a, axis=-1))
            if far is not None and np.any(far):
                idx = tuple(int(i) for i in np.argwhere(far)[0])
                raise CaptureError(
                    self.source,
                    f"the position at index {idx} is so far from the sample that its squared "
                    "distance overflows; give positions in the capture's unit",
                    name,
                )
        if np.any(pw < 0):
            raise CaptureError(self.source, "must be >= 0 (a light's intensity)", "light_power")
        if not float(self.side) > 0:
            raise CaptureError(self.source, f"must be a positive length, got {self.side}", "side")
        if ld is not None:
            norm = np.linalg.norm(ld, axis=-1, keepdims=True)
            if np.any(norm == 0):
                raise CaptureError(
                    self.source, "a direction is the zero vector; give unit vectors", "light_dir"
                )
            ld = ld / norm
        for name, v in (
            ("images", images),
            ("status", status),
            ("light_pos", lp),
            ("light_dir", ld),
            ("camera_pos", cp),
            ("light_power", np.array(pw)),
            ("points", pts),
            ("files", [Path(f) for f in self.files]),
            ("side", float(self.side)),
            ("source", None if self.source is None else Path(self.source)),
        ):
            object.__setattr__(self, name, v)

    # ------------------------------------------------------------------ shapes & status
    @property
    def shape(self) -> tuple[int, int, int, int]:
        """(K, H, W, C)."""
        return self.images.shape  # type: ignore[return-value]

    @property
    def n_photos(self) -> int:
        return self.images.shape[0]

    @property
    def is_point_light(self) -> bool:
        return self.light_pos is not None

    @property
    def valid(self) -> np.ndarray:
        """(K, H, W, C) bool: observations usable as values (status 0)."""
        return self.status == ObsStatus.OK

    @property
    def censored_high(self) -> np.ndarray:
        """(K, H, W, C) bool: saturated, true value >= ``saturation_level``."""
        return self.status == ObsStatus.SATURATED

    @property
    def censored_low(self) -> np.ndarray:
        """(K, H, W, C) bool: dark-clipped, true value <= ``dark_level``."""
        return self.status == ObsStatus.DARK

    def summary(self) -> dict[str, int]:
        """Number of observations per status name (every name, zeros included)."""
        # One comparison per code on the int8 array (bincount would first copy it to intp).
        return {
            name: int(np.count_nonzero(self.status == code)) for code, name in OBS_STATUS.items()
        }

    def __repr__(self) -> str:
        k, h, w, c = self.shape
        kind = "point" if self.is_point_light else "directional"
        return (
            f"Capture({self.layout}: {k} photos {h}x{w}x{c}, {self.transfer}, "
            f"{self.bit_depth}-bit, side {self.side:g} {self.unit}, {kind} lights, "
            f"source={str(self.source)!r})"
        )

    # ------------------------------------------------------------------ subsets
    def select(self, indices) -> Capture:
        """A new capture with the photos ``indices`` (ints or a boolean mask), in that order."""
        idx = np.arange(self.n_photos)[np.asarray(indices)]
        idx = np.atleast_1d(idx)
        if idx.size == 0:
            raise JaxreflError("select needs at least one photo")
        return replace(
            self,
            images=self.images[idx],
            status=self.status[idx],
            light_pos=None if self.light_pos is None else self.light_pos[idx],
            light_dir=None if self.light_dir is None else self.light_dir[idx],
            light_power=self.light_power[idx],
            camera_pos=self.camera_pos[idx],
            files=[self.files[i] for i in idx] if self.files else [],
            meta={**self.meta, "selected": [int(i) for i in idx]},
        )

    def crop(self, r0: int, r1: int, c0: int, c1: int) -> Capture:
        """Rows r0:r1 and columns c0:c1 (half-open) of every photo, points and status."""
        _, h, w, _ = self.shape
        if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w):
            raise JaxreflError(f"crop [{r0}:{r1}, {c0}:{c1}] is not inside the {h}x{w} photos")
        return replace(
            self,
            images=self.images[:, r0:r1, c0:c1],
            status=self.status[:, r0:r1, c0:c1],
            points=self.points[r0:r1, c0:c1],
        )

    def downsample(self, factor: int) -> Capture:
        """Box-filter the linear values by ``factor`` in both directions.

        H and W must be multiples of ``factor``. A block takes the status of the most
        severe observation in it (precedence in the module docstring), so any censored or
        invalid observation marks the whole block; a block with both saturated and dark
        observations becomes ``censored_mixed``. Points are the block means (the block
        centres), ``dark_level`` and ``saturation_level`` stay those of one observation.
        """
        f = int(factor)
        k, h, w, c = self.shape
        if f < 1 or h % f or w % f:
            raise JaxreflError(f"downsample factor {factor} must be >= 1 and divide {h}x{w}")
        if f == 1:
            return self
        blocks = (k, h // f, f, w // f, f, c)
        img = self.images.reshape(blocks).mean(axis=(2, 4), dtype=np.float64)
        st = self.status.reshape(blocks)
        # The most severe code of each block: max of the precedence ranks, mapped back.
        top = _RANK[st].max(axis=(2, 4))
        censored = (top == _RANK[ObsStatus.SATURATED]) | (top == _RANK[ObsStatus.DARK])
        mixed = (
            censored
            & np.any(st == ObsStatus.SATURATED, axis=(2, 4))
            & np.any(st == ObsStatus.DARK, axis=(2, 4))
        )
        out = np.where(mixed, np.uint8(ObsStatus.CENSORED_MIXED), _BY_RANK[top])
        pts = self.points.reshape(h // f, f, w // f, f, 3).mean(axis=(1, 3))
        return replace(self, images=img.astype(np.float32), status=out, points=pts)

    def apply_mask(self, keep: np.ndarray) -> Capture:
        """Mark observations outside ``keep`` ((H, W), (K, H, W) or (K, H, W, C) bool) masked."""
        keep = np.asarray(keep, bool)
        if keep.ndim == 2:
            keep = keep[None, :, :, None]
        elif keep.ndim == 3:
            keep = keep[..., None]
        try:
            drop = np.broadcast_to(~keep, self.shape)
        except ValueError:
            raise JaxreflError(
                f"mask of shape {keep.shape} does not fit photos {self.shape}"
            ) from None
        st = self.status.copy()
        # an invalid value (more severe than masked) keeps its code
        st[drop & (obs_severity(st) <= _RANK[ObsStatus.MASKED])] = ObsStatus.MASKED
        return replace(self, status=st)

    # ------------------------------------------------------------------ geometry
    def per_pixel_geometry(self, dtype=np.float32) -> dict[str, np.ndarray]:
        """wi, wo (K, H, W, 3), irradiance (K, H, W, C) and cos_i (K, H, W).

        Local frame = world frame (normal +z, tangent +x). wi and wo are unit vectors from
        each pixel towards the light and the camera (+z where the light sits on the point);
        irradiance is ``light_power / r^2`` for point lights (0 at r = 0) and
        ``light_power`` for directional ones; cos_i = max(wi_z, 0). The prediction of every
        observation is ``f_r(wi, wo) * irradiance * cos_i[..., None]``. Computed in float64
        and returned as ``dtype``; below the horizon the vectors stay finite (status 6/7).
        """
        k, h, w, c = self.shape
        wi = np.empty((k, h, w, 3), dtype)
        wo = np.empty((k, h, w, 3), dtype)
        irr = np.empty((k, h, w, c), dtype)
        cos_i = np.empty((k, h, w), dtype)
        pts = self.points
        for i in range(k):
            if self.light_pos is not None:
                d = self.light_pos[i] - pts
                r2 = np.sum(d * d, axis=-1)
                ok = r2 > 0
                # 1/r^2 is undefined on the light itself: 0 there, as PointLight does.
                inv = np.where(ok, 1.0 / np.where(ok, r2, 1.0), 0.0)
                wi_k = _unit_or_z(d)
                irr[i] = inv[..., None] * self.light_power[i]
            else:
                assert self.light_dir is not None  # __post_init__: light_pos or light_dir
                wi_k = np.broadcast_to(self.light_dir[i], pts.shape)
                irr[i] = self.light_power[i]
            wi[i] = wi_k
            # Light from below the plane does not reach the surface (as render does).
            cos_i[i] = np.maximum(wi_k[..., 2], 0.0)
            wo[i] = _unit_or_z(self.camera_pos[i] - pts)
        return {"wi": wi, "wo": wo, "irradiance": irr, "cos_i": cos_i}

    def lights(self) -> list:
        """The K lights as :mod:`jaxrefl.scene` objects (PointLight or DirectionalLight)."""
        from ..scene import DirectionalLight, PointLight

        if self.light_pos is not None:
            return [PointLight(p, e) for p, e in zip(self.light_pos, self.light_power, strict=True)]
        assert self.light_dir is not None  # __post_init__: light_pos or light_dir
        return [
            DirectionalLight(d, e) for d, e in zip(self.light_dir, self.light_power, strict=True)
        ]

    def cameras(self) -> list:
        """The K cameras as :class:`jaxrefl.scene.PinholeCamera` looking at the sample centre."""
        from ..scene import PinholeCamera

        return [PinholeCamera(p) for p in self.camera_pos]
