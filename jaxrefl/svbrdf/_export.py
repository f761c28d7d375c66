"""A fitted SVBRDF as textures, a Mitsuba 3 scene and a glTF 2.0 material.

:func:`renderer_maps` turns the maps of a fit (``maps.exr``, :class:`CaptureFit.maps`)
into the metallic-roughness parametrisation renderers take; :func:`write_textures` writes
them as files; :func:`mitsuba_scene` and :func:`gltf_document` reference those files.

Conversions
-----------
jaxrefl's capture models are a Lambertian base plus a Cook–Torrance GGX lobe with Schlick
Fresnel: f_r = albedo/pi + F0-Schlick D G / (4 cos_i cos_o) (:mod:`jaxrefl.svbrdf._models`).

* Roughness: jaxrefl fits the distribution's own width ``alpha``; glTF 2.0, Mitsuba's
  ``principled`` and Disney/Burley take perceptual roughness r with alpha = r^2, so the
  roughness texture is sqrt(alpha) (:func:`jaxrefl.brdf.alpha_to_roughness`).
* Specular colour: the metallic-roughness view (base colour b, metallic m; dielectric
  F0_d = 0.04) of the fitted (albedo, F0) by :func:`jaxrefl.brdf.specular_to_metallic`, for
  every model: grey F0 <= 0.04 gives m = 0 (a plain dielectric), a brighter or coloured F0
  (``ggx_rgb``, ``pooled``; a grey dielectric F0 up to 0.25) partly metallic. The glTF
  core BRDF weights the diffuse base by (1 - F0_d) (glTF 2.0 spec, appendix B), Mitsuba's
  ``principled`` does not (its diffuse is base (1 - m)/pi near normal incidence, checked
  by ``tests/test_export.py``), so each gets its own base colour solving
  b (1 - F0_d)(1 - m) = albedo (glTF) or b (1 - m) = albedo (Mitsuba). Where (albedo, F0)
  is not a metallic-roughness material (a grey F0 other than 0.04 under a coloured
  albedo), both are the nearest one in the least-squares sense of
  :func:`~jaxrefl.brdf.specular_to_metallic`.
* Mitsuba ``principled`` takes ``specular`` as one float in [0, 1], F0 = 0.08 specular for
  its dielectric lobe; per-pixel F0 goes through the metallic texture, with
  ``specular = 0.5`` (F0 = 0.04, glTF's F0_d). ``specular.exr`` holds the per-pixel
  principled value F0/0.08 of a grey F0, clipped to [0, 1] (F0 <= 0.08; the fits allow up
  to 0.25), for renderers that take a specular texture (Blender's Principled BSDF).
* Near normal incidence, with the light beside the camera (half vector = view), the
  Schlick factor is F0 exactly and Mitsuba's ``principled`` equals jaxrefl's model; Burley's
  diffuse retro-reflection, Mitsuba's dielectric Fresnel and its uncorrelated Smith G
  differ from jaxrefl's at grazing angles.
* Normals (``ggx_normal``): the unit shading normal in the sample frame (x along the
  columns, y up the rows, z out of the sample) is a tangent-space normal map with
  +X right, +Y up (glTF, OpenGL convention), encoded as (n + 1)/2.

Textures (:func:`write_textures`): ``base_color.png`` (sRGB, 8 or 16 bit),
``roughness.png``, ``metallic.png`` (linear, one grey channel), ``normal.png`` (when
normals were fitted), and float32 single-layer EXRs with standard channel names
(``R, G, B`` or ``Y``): ``base_color.exr`` (linear, glTF convention),
``base_color_principled.exr``, ``roughness.exr``, ``metallic.exr``,
``metallic_principled.exr``, ``specular.exr``, ``normal.exr`` and the fitted
``albedo.exr``, ``f0.exr``, ``alpha.exr``. Pixels without an estimate (NaN) are written
as 0 (black, smooth, dielectric) and listed in :attr:`Textures.missing`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxrefl import brdf
from jaxrefl._errors import JaxreflError
from jaxrefl.io import map_key, write_text_atomic

__all__ = [
    "F0_DIELECTRIC",
    "FlashView",
    "RendererMaps",
    "Textures",
    "gltf_document",
    "mitsuba_scene",
    "mitsuba_xml",
    "read_maps",
    "renderer_maps",
    "write_gltf",
    "write_mitsuba",
    "write_textures",
]

F0_DIELECTRIC = brdf.DIELECTRIC_F0_DEFAULT  # glTF's and principled (specular = 0.5) F0_d
_PRINCIPLED_F0_PER_SPECULAR = 0.08  # Mitsuba/Disney principled: F0 = 0.08 specular


def read_maps(fit_dir: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(maps by :func:`jaxrefl.io.map_name`, metadata) of ``fit_dir/maps.exr`` (or of the
    ``.exr`` file ``fit_dir`` names)."""
    from jaxrefl.io import read_exr

    path = Path(fit_dir)
    path = path / "maps.exr" if path.is_dir() else path
    if not path.exists():
        raise FileNotFoundError(2, f"no maps.exr at {path}: give a `jaxrefl fit` output folder")
    exr = read_exr(path)
    if "status.Y" not in exr.channels:
        raise JaxreflError(
            f"{path}: no channel status.Y; not a maps.exr of this jaxrefl version (refit it)"
        )
    return {map_key(k): v for k, v in exr.channels.items()}, exr.metadata


@dataclass(frozen=True)
class RendererMaps:
    """The fit in the conventions renderers take (module docstring), (H, W[, 3]) float32.

    albedo, f0, alpha: the fitted maps (F0 as RGB); roughness = sqrt(alpha);
    base_color, metallic: glTF 2.0's metallic-roughness view; base_color_principled,
    metallic_principled: Mitsuba ``principled``'s (no (1 - F0_d) diffuse weight);
    specular: principled's F0/0.08 of the mean F0, clipped to [0, 1]; normal: unit
    shading normal (sample frame) or None; missing: pixels without an estimate.
    """

    albedo: np.ndarray
    f0: np.ndarray
    alpha: np.ndarray
    roughness: np.ndarray
    base_color: np.ndarray
    metallic: np.ndarray
    base_color_principled: np.ndarray
    metallic_principled: np.ndarray
    specular: np.ndarray
    normal: np.ndarray | None
    missing: np.ndarray


def _rgb(maps: Mapping[str, np.ndarray], name: str) -> np.ndarray:
    if f"{name}.R" in maps:
        return np.stack([maps[f"{name}.{c}"] for c in "RGB"], -1)
    if name in maps:
        return np.repeat(np.asarray(maps[name])[..., None], 3, -1)
    raise JaxreflError(f"the maps have no {name!r} (channels {name}.R/G/B or {name}.Y)")


def renderer_maps(maps: Mapping[str, np.ndarray]) -> RendererMaps:
    """The metallic-roughness view of a fit's maps (keys :func:`jaxrefl.io.map_name`:
    ``albedo.R/G/B``, ``specular`` or ``specular.R/G/B``, ``alpha``, ``normal.X/Y/Z``).
    A Lambertian fit (no ``specular``) gets F0 = 0.04 and alpha = 1, a rough dielectric."""
    albedo = _rgb(maps, "albedo").astype(np.float64)
    shape = albedo.shape[:-1]
    lambert = "specular" not in maps and "specular.R" not in maps
    f0 = np.full(albedo.shape, F0_DIELECTRIC) if lambert else _rgb(maps, "specular")
    alpha = np.ones(shape) if lambert else np.asarray(maps["alpha"], np.float64)
    missing = ~(np.all(np.isfinite(albedo), -1) & np.all(np.isfinite(f0), -1))
    missing |= ~np.isfinite(alpha)
    albedo = np.where(missing[..., None], 0.0, albedo)
    f0 = np.where(missing[..., None], F0_DIELECTRIC, f0)
    alpha = np.where(missing, 1.0, alpha)
    base, metal = brdf.specular_to_metallic(jnp.asarray(albedo), jnp.asarray(f0))
    # b (1 - m) = albedo is specular_to_metallic's b (1 - F0_d)(1 - m) = albedo (1 - F0_d).
    base_p, metal_p = brdf.specular_to_metallic(
        jnp.asarray(albedo * (1.0 - F0_DIELECTRIC)), jnp.asarray(f0)
    )
    # principled's specular is in [0, 1]: F0 above 0.08 does not fit, it is clipped.
    spec = np.clip(f0.mean(-1) / _PRINCIPLED_F0_PER_SPECULAR, 0.0, 1.0)
    normal = None
    if "normal.X" in maps:
        normal = np.stack([maps[f"normal.{a}"] for a in "XYZ"], -1).astype(np.float64)
        normal = np.where(missing[..., None] | ~np.isfinite(normal), [0.0, 0.0, 1.0], normal)

    def f32(a):
        return np.asarray(a, np.float32)

    return RendererMaps(
        albedo=f32(albedo),
        f0=f32(f0),
        alpha=f32(alpha),
        roughness=f32(brdf.alpha_to_roughness(jnp.asarray(alpha))),
        base_color=f32(base),
        metallic=f32(metal),
        base_color_principled=f32(base_p),
        metallic_principled=f32(metal_p),
        specular=f32(spec),
        normal=None if normal is None else f32(normal),
        missing=missing,
    )


@dataclass(frozen=True)
class Textures:
    """Texture files written by :func:`write_textures`: ``files`` maps a role
    (``base_color``, ``base_color_exr``, ``roughness``, ...) to a file name in ``folder``."""

    folder: Path
    files: dict[str, str]
    size: tuple[int, int]
    missing: int

    def path(self, role: str) -> Path:
        return self.folder / self.files[role]


def _quantise(x: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    q = np.round(np.clip(np.nan_to_num(x), 0.0, 1.0) * top)
    return q.astype(np.uint8 if bits == 8 else np.uint16)


def write_textures(
    fit: str | Path | Mapping[str, np.ndarray] | RendererMaps, out_dir: str | Path, bits: int = 8
) -> Textures:
    """Write the texture files (module docstring) into ``out_dir`` (created if missing).

    fit: a ``jaxrefl fit`` output folder or its ``maps.exr`` (:func:`read_maps`), a fit's
         maps (:attr:`CaptureFit.maps`) or their :func:`renderer_maps`;
    bits: 8 or 16, the PNGs' sample depth.
    """
    from jaxrefl.io import write_exr, write_exr_rgb, write_png
    from jaxrefl.scene import SRGBResponse

    if bits not in (8, 16):
        raise JaxreflError(f"PNG textures are 8 or 16 bit, not {bits}")
    if isinstance(fit, str | Path):
        fit = read_maps(fit)[0]
    rm = fit if isinstance(fit, RendererMaps) else renderer_maps(fit)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, str] = {}

    def png(role: str, img: np.ndarray) -> None:
        files[role] = f"{role}.png"
        write_png(out / files[role], _quantise(img, bits))

    def exr(role: str, img: np.ndarray) -> None:
        files[f"{role}_exr"] = f"{role}.exr"
        if img.ndim == 3:
            write_exr_rgb(out / files[f"{role}_exr"], img)
        else:
            write_exr(out / files[f"{role}_exr"], {"Y": img})

    png("base_color", np.asarray(SRGBResponse().curve(jnp.asarray(rm.base_color))))
    png("roughness", rm.roughness)
    png("metallic", rm.metallic)
    # glTF's packed texture: roughness in G, metallic in B (R: unused, 1).
    png("metallic_roughness", np.stack([np.ones_like(rm.alpha), rm.roughness, rm.metallic], -1))
    for role in ("base_color", "base_color_principled", "roughness", "metallic"):
        exr(role, getattr(rm, role))
    exr("metallic_principled", rm.metallic_principled)
    exr("specular", rm.specular)
    exr("albedo", rm.albedo)
    exr("f0", rm.f0)
    exr("alpha", rm.alpha)
    if rm.normal is not None:
        enc = 0.5 * (rm.normal + 1.0)
        png("normal", enc)
        exr("normal", enc)
    h, w = rm.alpha.shape
    return Textures(out, files, (h, w), int(np.count_nonzero(rm.missing)))


@dataclass(frozen=True)
class FlashView:
    """A square sample of side ``side`` (scene units) on z = 0 centred at the origin, seen
    from ``distance`` straight above by a pinhole camera whose field of view is the
    sample, with a point light of ``intensity`` (W/sr) at the camera (a phone's flash)."""

    side: float = 2.0
    distance: float = 4.0
    intensity: float = 10.0
    width: int = 256
    height: int = 256
    spp: int = 16

    def __post_init__(self) -> None:
        for name in ("side", "distance", "intensity", "width", "height", "spp"):
            if not getattr(self, name) > 0:
                raise JaxreflError(f"FlashView.{name} must be positive, got {getattr(self, name)}")

    @property
    def fov(self) -> float:
        """Horizontal field of view in degrees: the sample's side fills the image width."""
        return 2.0 * math.degrees(math.atan(0.5 * self.side / self.distance))


@dataclass(frozen=True)
class _Transform:
    """A transform of the scene description: ``look_at`` (origin, target, up), ``scale``
    (x, y, z) or ``flip_v`` (v -> 1 - v of a texture's coordinates)."""

    kind: str
    args: tuple[tuple[float, ...], ...] = ()


# Mitsuba's rectangle has v = 0 at y = -1, where the image's last row belongs: v is flipped
# so that row 0 lies at +y, as in the sample frame.
_FLIP_V = _Transform("flip_v")


def _bitmap(tex: Textures, role: str, raw: bool = False) -> dict[str, Any]:
    return {
        "type": "bitmap",
        "filename": tex.files[role],
        "raw": raw,
        "wrap_mode": "clamp",
        "to_uv": _FLIP_V,
    }


def _scene(tex: Textures, view: FlashView | None) -> dict[str, Any]:
    """The scene of :func:`mitsuba_scene` with file names relative to ``tex.folder`` and
    transforms as :class:`_Transform`."""
    v = view or FlashView()
    bsdf: dict[str, Any] = {
        "type": "principled",
        "base_color": _bitmap(tex, "base_color_principled_exr"),
        "metallic": _bitmap(tex, "metallic_principled_exr"),
        "roughness": _bitmap(tex, "roughness_exr"),
        "specular": 0.5,
    }
    if "normal_exr" in tex.files:
        normalmap = _bitmap(tex, "normal_exr", raw=True)
        bsdf = {"type": "normalmap", "normalmap": normalmap, "bsdf": bsdf}
    eye = (0.0, 0.0, float(v.distance))
    return {
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {
            "type": "perspective",
            "fov": v.fov,
            "fov_axis": "x",
            "to_world": _Transform("look_at", (eye, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))),
            "film": {
                "type": "hdrfilm",
                "width": v.width,
                "height": v.height,
                "rfilter": {"type": "box"},
            },
            "sampler": {"type": "independent", "sample_count": v.spp},
        },
        "flash": {"type": "point", "position": eye, "intensity": ("rgb", float(v.intensity))},
        "sample": {
            "type": "rectangle",
            "to_world": _Transform("scale", ((0.5 * v.side, 0.5 * v.side, 1.0),)),
            "bsdf": bsdf,
        },
    }


def mitsuba_scene(tex: Textures, view: FlashView | None = None) -> dict[str, Any]:
    """A Mitsuba 3 scene dict for ``mitsuba.load_dict`` (a Mitsuba variant must be set): the
    sample as a ``rectangle`` with a ``principled`` BSDF textured by the linear EXRs
    (``base_color_principled``, ``metallic_principled``, ``roughness``; ``specular`` 0.5;
    module docstring), inside a ``normalmap`` BSDF when normals were fitted, under ``view``
    (:class:`FlashView`), rendered by the ``direct`` integrator (a point light needs no
    more). Needs the ``mitsuba`` package (``pip install jaxrefl[render]``)."""
    try:
        import mitsuba as mi
    except ImportError:
        raise ImportError(
            "mitsuba_scene needs the mitsuba package: pip install 'jaxrefl[render]'"
        ) from None
    T = mi.ScalarTransform4f

    def conv(key: str, x: Any) -> Any:
        if isinstance(x, dict):
            return {k: conv(k, y) for k, y in x.items()}
        if isinstance(x, _Transform):
            if x.kind == "look_at":
                o, t, u = x.args
                return T().look_at(origin=list(o), target=list(t), up=list(u))
            if x.kind == "scale":
                return T().scale(list(x.args[0]))
            return T().translate([0.0, 1.0, 0.0]).scale([1.0, -1.0, 1.0])  # flip_v
        if isinstance(x, tuple) and x and x[0] == "rgb":
            return {"type": "rgb", "value": x[1]}
        if key == "filename":
            return str(tex.folder / x)
        return x

    return conv("", _scene(tex, view))


# XML tag of a nested plugin by its key in the scene description.
_XML_TAGS = {
    "integrator": "integrator",
    "sensor": "sensor",
    "film": "film",
    "rfilter": "rfilter",
    "sampler": "sampler",
    "flash": "emitter",
    "sample": "shape",
    "bsdf": "bsdf",
}


def mitsuba_xml(tex: Textures, view: FlashView | None = None) -> str:
    """:func:`mitsuba_scene` as Mitsuba 3 XML (``mitsuba.load_file``), the texture paths
    relative to the file when it is saved in ``tex.folder``; needs no mitsuba package."""
    from xml.sax.saxutils import quoteattr

    def num(v: float) -> str:
        return repr(float(v))

    def element(key: str, value: Any, pad: str) -> list[str]:
        if isinstance(value, dict):
            tag = _XML_TAGS.get(key, "texture")
            name = "" if key in _XML_TAGS or key == "" else f" name={quoteattr(key)}"
            head = f"{pad}<{tag} type={quoteattr(value['type'])}{name}>"
            if key == "":
                head = f'{pad}<scene version="3.0.0">'
            body = [ln for k, v in value.items() if k != "type" for ln in element(k, v, pad + "  ")]
            return [head, *body, f"{pad}</{'scene' if key == '' else tag}>"]
        n = quoteattr(key)
        if isinstance(value, _Transform):
            if value.kind == "look_at":
                o, t, u = (",".join(num(c) for c in a) for a in value.args)
                inner = f"<lookat origin={quoteattr(o)} target={quoteattr(t)} up={quoteattr(u)}/>"
            elif value.kind == "scale":
                x, y, z = (num(c) for c in value.args[0])
                inner = f'<scale x="{x}" y="{y}" z="{z}"/>'
            else:  # flip_v: v -> 1 - v
                inner = '<scale y="-1"/><translate y="1"/>'
            return [f"{pad}<transform name={n}>{inner}</transform>"]
        if isinstance(value, tuple) and value and value[0] == "rgb":
            return [f'{pad}<rgb name={n} value="{num(value[1])}"/>']
        if isinstance(value, tuple):
            x, y, z = (num(c) for c in value)
            return [f'{pad}<point name={n} x="{x}" y="{y}" z="{z}"/>']
        if isinstance(value, bool):
            return [f'{pad}<boolean name={n} value="{str(value).lower()}"/>']
        if isinstance(value, int):
            return [f'{pad}<integer name={n} value="{value}"/>']
        if isinstance(value, float):
            return [f'{pad}<float name={n} value="{num(value)}"/>']
        return [f"{pad}<string name={n} value={quoteattr(str(value))}/>"]

    return "\n".join(element("", _scene(tex, view), "")) + "\n"


# glTF 2.0 constants: sampler filters and wrap, accessor component types, buffer targets.
_LINEAR, _CLAMP = 9729, 33071
_FLOAT, _UINT16 = 5126, 5123
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def gltf_document(tex: Textures, side: float = 1.0, name: str = "jaxrefl_fit") -> dict[str, Any]:
    """A glTF 2.0 document (the ``.gltf`` JSON): one square of side ``side`` (metres, glTF's
    unit) in the xy plane facing +z, texture coordinates with (0, 0) at the image's top
    left corner at (-side/2, +side/2), and one metallic-roughness material using
    ``base_color.png`` (sRGB), ``metallic_roughness.png`` (G roughness, B metallic) and,
    when normals were fitted, ``normal.png`` (tangent space, +X right, +Y up; the
    tangent is +x). The geometry is embedded as a base64 data URI; images are referenced
    by file name, relative to ``tex.folder``."""
    import base64

    h = 0.5 * side
    pos = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], np.float32)
    nrm = np.tile(np.array([0, 0, 1], np.float32), (4, 1))
    tan = np.tile(np.array([1, 0, 0, 1], np.float32), (4, 1))
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    idx = np.array([0, 3, 2, 0, 2, 1], np.uint16)  # counter-clockwise seen from +z
    blobs = [pos, nrm, tan, uv]
    views, accessors, offset = [], [], 0
    types = {3: "VEC3", 4: "VEC4", 2: "VEC2"}
    for arr in blobs:
        views.append(
            {"buffer": 0, "byteOffset": offset, "byteLength": arr.nbytes, "target": _ARRAY_BUFFER}
        )
        acc: dict[str, Any] = {
            "bufferView": len(views) - 1,
            "componentType": _FLOAT,
            "count": 4,
            "type": types[arr.shape[1]],
        }
        if arr is pos:
            acc["min"], acc["max"] = pos.min(0).tolist(), pos.max(0).tolist()
        accessors.append(acc)
        offset += arr.nbytes
    views.append(
        {
            "buffer": 0,
            "byteOffset": offset,
            "byteLength": idx.nbytes,
            "target": _ELEMENT_ARRAY_BUFFER,
        }
    )
    accessors.append(
        {"bufferView": len(views) - 1, "componentType": _UINT16, "count": 6, "type": "SCALAR"}
    )
    data = b"".join(a.tobytes() for a in blobs) + idx.tobytes()
    images = [{"uri": tex.files["base_color"]}, {"uri": tex.files["metallic_roughness"]}]
    material: dict[str, Any] = {
        "name": name,
        "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0},
            "metallicRoughnessTexture": {"index": 1},
            "metallicFactor": 1.0,
            "roughnessFactor": 1.0,
        },
    }
    if "normal" in tex.files:
        images.append({"uri": tex.files["normal"]})
        material["normalTexture"] = {"index": 2}
    return {
        "asset": {"version": "2.0", "generator": "jaxrefl"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [
            {
                "primitives": [
                    {
                        "attributes": {"POSITION": 0, "NORMAL": 1, "TANGENT": 2, "TEXCOORD_0": 3},
                        "indices": 4,
                        "material": 0,
                    }
                ]
            }
        ],
        "materials": [material],
        "textures": [{"sampler": 0, "source": i} for i in range(len(images))],
        "images": images,
        "samplers": [
            {"magFilter": _LINEAR, "minFilter": _LINEAR, "wrapS": _CLAMP, "wrapT": _CLAMP}
        ],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [
            {
                "byteLength": len(data),
                "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode(),
            }
        ],
    }


def write_mitsuba(
    fit: str | Path | Mapping[str, np.ndarray],
    out_dir: str | Path,
    view: FlashView | None = None,
    bits: int = 8,
) -> list[Path]:
    """The textures (:func:`write_textures`) and ``scene.xml`` (:func:`mitsuba_xml`) of a
    fit (a ``jaxrefl fit`` folder, a ``maps.exr`` or a maps dict) in ``out_dir``; returns
    the paths written. Render with ``mitsuba scene.xml`` or ``mi.load_file``."""
    tex = write_textures(fit, out_dir, bits)
    xml = write_text_atomic(tex.folder / "scene.xml", mitsuba_xml(tex, view))
    return [*(tex.folder / f for f in tex.files.values()), xml]


def write_gltf(
    fit: str | Path | Mapping[str, np.ndarray],
    out_dir: str | Path,
    side: float = 1.0,
    bits: int = 8,
) -> list[Path]:
    """The textures and ``material.gltf`` (:func:`gltf_document`) of a fit in ``out_dir``;
    returns the paths written."""
    tex = write_textures(fit, out_dir, bits)
    doc = write_text_atomic(
        tex.folder / "material.gltf", json.dumps(gltf_document(tex, side), indent=1)
    )
    return [*(tex.folder / f for f in tex.files.values()), doc]
