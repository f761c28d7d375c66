"""Reading flash captures from disk: three layouts, one :class:`~jaxrefl.io.Capture`.

:func:`load_capture` recognises the layout of a folder by the file it finds first:

``capture.json`` -- generic (ours, written by :func:`~jaxrefl.io.save_generic_capture`,
:mod:`._capture_save`)::

    {
      "images":   ["00.exr", "01.exr", ...],          # K files, relative to the folder
      "transfer": "linear" | "srgb" | "gamma2.2" | {"x": [...], "y": [...]},
      "side":     11.136,                              # side S of the imaged square
      "unit":     "cm",                                # optional, default "cm"
      "lights":   [{"type": "point", "position": [x, y, z], "power": [r, g, b]}
                   | {"type": "directional", "direction": [x, y, z],
                      "irradiance": [r, g, b]}, ...],  # K entries, or 1 for all
      "cameras":  [{"position": [x, y, z]}, ...],      # K entries, or 1 for all
      "mask":       "mask.png",                        # optional: 0 = excluded pixel
      "saturation": 4.0                                # optional: linear level at and
    }                                                  # above which a value is clipped

    ``transfer`` decodes file values to linear ones: "linear" (EXR, or a linear PNG),
    "srgb" (IEC 61966-2-1), "gammaG" (value^G, e.g. "gamma2.2") or a tabulated camera
    response {"x": linear values, "y": encoded values in [0, 1]}, both increasing
    (:class:`jaxrefl.scene.TabulatedResponse`). ``power`` and ``irradiance`` are one number
    or one per channel; all lights are of one type. Images are EXR (R, G, B or Y, optional
    A) or PNG/any 8-bit format Pillow reads.

``parameters.json`` or ``optim.json`` -- svbrdf-diff-renderer (Guo,
``tflsguoyu/svbrdf-diff-renderer``)::

    {"image_size": S, "idx": [0, 1, ...], "camera_pos": [[x, y, z], ...],
     "light_pos": [[x, y, z], ...], "light_pow": ..., "images_dir": "images",
     "gamma": 2.2}                                     # gamma: optional (our demo)

    Photo k is ``<images_dir>/reference/<N>/<idx[k]:02d>.png`` with camera
    ``camera_pos[idx[k]]`` and light ``light_pos[idx[k]]`` (as that renderer indexes them).
    ``<N>`` is the resolution folder: the only one, the largest, or ``resolution=``.
    ``light_pow`` is one number; one value per channel (the real data: [1500, 1500, 1500]);
    one value per photo (our demo); or per photo and channel. A list as long as both the
    channel count and the photo list counts as per channel.

    The layout that tool writes since 2024 keeps the same lists in ``optim.json``, with
    ``im_size`` for ``image_size`` and ``target_dir`` (e.g. ``"target/1024"``) naming the
    photo folder itself; ``resolution=`` picks a sibling ``target/<N>`` folder if there is
    one. Its other keys (``optimize_dir``, ``rerender_dir``: the optimiser's output folders)
    are not read. ``parameters.json`` wins where a folder holds both.

MaterialGAN (Guo et al. 2020) -- the photos ``NN.png`` (numeric names, in numeric order;
other PNGs such as ``rendered.png`` are ignored) beside ``camera_pos.txt``,
``light_pos.txt``, ``light_power.txt`` and ``image_size.txt``: comma-separated numbers, one
line per photo (``light_power.txt`` may hold one line for all photos, ``image_size.txt``
one number). Without ``light_pos.txt`` the flash is taken to sit at the camera (the
MaterialGAN tools write ``light_pos.txt`` as a copy of ``camera_pos.txt``); ``meta`` says so.

Both public layouts store 8-bit photos encoded as value^(1/2.2) clipped to [0, 1] (the
MaterialGAN convention, Guo et al. 2020), decoded here as value^2.2, lengths in cm.

Pixels (:mod:`jaxrefl.io._photos`): 8- and 16-bit PNGs are read at full depth, grey images
give C = 1, an alpha channel becomes a mask (alpha = 0 -> status ``masked``); the codes of
every observation are listed in :mod:`jaxrefl.io._capture`. Errors are
:class:`CaptureError` naming the file and the field. What is read is then checked for
physical sense (:mod:`jaxrefl.io._capture_checks`): cameras and lights above the sample at a
sane distance, light powers > 0, photos that measured something; what is merely odd is a
:class:`~jaxrefl.io.CaptureWarning`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from jaxrefl._errors import JaxreflError

from ._capture import Capture, CaptureError, geometry_status
from ._capture_checks import Fields, check_geometry, check_photos
from ._capture_fields import (
    _get,
    _light_power,
    _positive,
    _read_json,
    _read_txt,
    _vectors,
)
from ._photos import Photos, read_pixels, x64

__all__ = ["load_capture"]

_LAYOUTS = ("generic", "svbrdf-diff-renderer", "materialgan")
_EXPECTED = (
    "capture.json (generic); parameters.json + images/reference/<N>/NN.png or optim.json "
    "+ <target_dir>/NN.png (svbrdf-diff-renderer); camera_pos.txt, light_pos.txt, "
    "light_power.txt, image_size.txt beside NN.png (MaterialGAN)"
)
_MG_FILES = ("camera_pos.txt", "light_pos.txt", "light_power.txt", "image_size.txt")


def _finish(
    photos: Photos,
    files: list[Path],
    *,
    layout: str,
    source: Path,
    side: float,
    camera_pos: np.ndarray,
    light_power: np.ndarray,
    fields: Fields,
    light_pos=None,
    light_dir=None,
    unit: str = "cm",
    meta=None,
    mask: np.ndarray | None = None,
) -> Capture:
    """The capture, after the physical checks (:mod:`jaxrefl.io._capture_checks`) of its
    geometry (before any is computed) and of its photos (after the mask)."""
    from ..scene import planar_points

    check_geometry(camera_pos, light_pos, light_dir, light_power, side, fields, unit)
    _, h, w, _ = photos.images.shape
    with x64():
        points = np.asarray(planar_points(h, w, side, dtype=np.float64), np.float64)
    status = geometry_status(photos.status, points, light_pos, light_dir, camera_pos)
    cap = Capture(
        images=photos.images,
        status=status,
        light_pos=light_pos,
        light_dir=light_dir,
        light_power=light_power,
        camera_pos=camera_pos,
        side=side,
        points=points,
        layout=layout,
        source=source,
        files=files,
        transfer=photos.transfer,
        bit_depth=photos.bit_depth,
        unit=unit,
        dark_level=photos.dark_level,
        saturation_level=photos.saturation_level,
        meta=dict(meta or {}),
    )
    cap = cap if mask is None else cap.apply_mask(mask)
    check_photos(cap, fields)
    return cap


def _resolution_folder(ref: Path, resolution: int | None) -> tuple[Path, int]:
    found = (
        sorted((int(d.name), d) for d in ref.iterdir() if d.is_dir() and d.name.isdigit())
        if ref.is_dir()
        else []
    )
    if not found:
        raise CaptureError(ref, "no resolution folder; expected <images_dir>/reference/<N>/NN.png")
    sizes = [n for n, _ in found]
    if resolution is None:
        return found[-1][1], found[-1][0]
    for n, d in found:
        if n == resolution:
            return d, n
    for n, d in found:  # a larger folder to box-downsample from
        if n > resolution and n % resolution == 0:
            return d, n
    raise CaptureError(ref, f"no folder for resolution {resolution}; available: {sizes}")


def _target_folder(folder: Path, pj: Path, target: str, resolution: int | None):
    """The photo folder named by ``optim.json``'s ``target_dir`` (e.g. ``target/1024``):
    that folder, or a sibling resolution folder when ``resolution`` asks for another."""
    named = folder / target
    if not named.is_dir():
        raise CaptureError(pj, f"names {target!r}, but {named} is not a folder", "target_dir")
    if resolution is None or not named.name.isdigit():
        return named, int(named.name) if named.name.isdigit() else None
    return _resolution_folder(named.parent, resolution)


def _load_svbrdf(folder: Path, resolution, max_photos, file: str = "parameters.json") -> Capture:
    """The svbrdf-diff-renderer layouts: ``parameters.json`` (``image_size``,
    ``images_dir``/reference/<N>) and, since 2024, ``optim.json`` (``im_size``,
    ``target_dir`` naming the photo folder itself)."""
    pj = folder / file
    data = _read_json(pj)
    newer = file == "optim.json"
    size_key = "im_size" if newer else "image_size"
    side = _positive(_get(data, size_key, pj), pj, size_key)
    cams = _vectors(_get(data, "camera_pos", pj), pj, "camera_pos")
    lights = _vectors(_get(data, "light_pos", pj), pj, "light_pos")
    if len(cams) != len(lights):
        raise CaptureError(
            pj, f"has {len(lights)} entries but camera_pos has {len(cams)}", "light_pos"
        )
    idx_raw = data.get("idx", list(range(len(cams))))
    try:
        idx = np.asarray(idx_raw)
        ok = idx.ndim == 1 and idx.size > 0 and np.issubdtype(idx.dtype, np.integer)
    except (TypeError, ValueError):
        ok = False
    if not ok or np.any(idx < 0) or np.any(idx >= len(cams)):
        raise CaptureError(
            pj,
            f"{idx_raw!r} must be photo indices 0..{len(cams) - 1} (one per entry of "
            f"camera_pos/light_pos, which have {len(cams)})",
            "idx",
        )
    idx = idx[:max_photos] if max_photos else idx
    if newer:
        target = _get(data, "target_dir", pj)
        if not isinstance(target, str) or not target:
            raise CaptureError(pj, f"expected a folder name, got {target!r}", "target_dir")
        res_dir, n = _target_folder(folder, pj, target, resolution)
        listed = "target_dir"
    else:
        images_dir = folder / str(data.get("images_dir", "images"))
        res_dir, n = _resolution_folder(images_dir / "reference", resolution)
        listed = "idx"
    files = []
    for i in idx:
        cands = [res_dir / f"{i:02d}.png", res_dir / f"{i}.png"]
        f = next((c for c in cands if c.is_file()), None)
        if f is None:
            raise CaptureError(
                pj, f"photo {int(i)} listed in idx: {cands[0]} does not exist", listed
            )
        files.append(f)
    gamma = _positive(data.get("gamma", 2.2), pj, "gamma")
    photos = Photos(files, f"gamma{gamma!r}", pj)
    c = photos.images.shape[-1]
    power = _light_power(_get(data, "light_pow", pj), len(cams), idx, c, pj, "light_pow")
    meta = {"idx": [int(i) for i in idx], "resolution_folder": n, "parameters_file": file}
    fields = Fields(
        camera=(pj, [f"camera_pos[{i}]" for i in idx]),
        light=(pj, [f"light_pos[{i}]" for i in idx]),
        power=(pj, ["light_pow"] * idx.size),
        phone=True,
    )
    return _finish(
        photos,
        files,
        layout="svbrdf-diff-renderer",
        source=folder,
        side=side,
        camera_pos=cams[idx],
        light_pos=lights[idx],
        light_power=power,
        fields=fields,
        meta=meta,
    )


def _load_materialgan(folder: Path, resolution, max_photos) -> Capture:
    files = sorted((p for p in folder.glob("*.png") if p.stem.isdigit()), key=lambda p: int(p.stem))
    if not files:
        raise CaptureError(folder, "no photos NN.png beside camera_pos.txt (MaterialGAN layout)")
    n = len(files)
    names = f"{files[0].name} ... {files[-1].name}"
    cams = _read_txt(folder / "camera_pos.txt")
    lp_file = folder / "light_pos.txt"
    meta: dict[str, Any] = {}
    if lp_file.exists():
        lights = _read_txt(lp_file)
    else:
        lights = cams
        meta["light_pos"] = "camera_pos.txt (co-located flash: no light_pos.txt)"
    for fname, a in (("camera_pos.txt", cams), ("light_pos.txt", lights)):
        if a.shape != (n, 3):
            raise CaptureError(
                folder / fname,
                f"has {a.shape[0]} lines of {a.shape[1]} numbers but there are "
                f"{n} photos ({names}); expected {n} lines x, y, z",
            )
    side_a = _read_txt(folder / "image_size.txt")
    side = _positive(side_a, folder / "image_size.txt", "image_size")
    if side_a.size not in (1, n):
        raise CaptureError(
            folder / "image_size.txt", f"expected 1 or {n} numbers, got {side_a.size}"
        )
    rows = np.arange(min(n, max_photos) if max_photos else n)
    files = files[: rows.size]
    photos = Photos(files, "gamma2.2", folder / "camera_pos.txt")
    c = photos.images.shape[-1]
    pw_file = folder / "light_power.txt"
    pw = _read_txt(pw_file)
    if pw.shape[0] not in (1, n):
        raise CaptureError(pw_file, f"has {pw.shape[0]} lines; expected 1 or {n} (one per photo)")
    power = _light_power(pw, n, rows, c, pw_file, "light_power")
    lines = [f"line {r + 1}" for r in rows]
    fields = Fields(
        camera=(folder / "camera_pos.txt", lines),
        light=(lp_file if lp_file.exists() else folder / "camera_pos.txt", lines),
        power=(pw_file, lines if pw.shape[0] == n else ["line 1"] * rows.size),
        phone=True,
    )
    return _finish(
        photos,
        files,
        layout="materialgan",
        source=folder,
        side=side,
        camera_pos=cams[rows],
        light_pos=lights[rows],
        light_power=power,
        fields=fields,
        meta=meta,
    )


def _per_photo(value, k: int, path: Path, field: str) -> list[dict]:
    items = [value] if isinstance(value, dict) else value
    if (
        not isinstance(items, list)
        or len(items) not in (1, k)
        or not all(isinstance(v, dict) for v in items)
    ):
        raise CaptureError(path, f"expected a list of 1 or {k} objects (one per image)", field)
    return items * k if len(items) == 1 else items


def _entry_names(key: str, value, k: int) -> list[str]:
    """The JSON path of each photo's entry: ``key[i]``, or ``key[0]`` / ``key`` where one
    entry serves every photo (:func:`_per_photo`)."""
    if isinstance(value, dict):
        return [key] * k
    return [f"{key}[{i if len(value) == k else 0}]" for i in range(k)]


def _lt_get(lt: dict, key: str, path: Path, i: int):
    if key not in lt:
        raise CaptureError(path, f"missing key {key!r}", f"lights[{i}].{key}")
    return lt[key]


def _entry(obj: dict, key: str, path: Path, where: str) -> np.ndarray:
    """One [x, y, z] from ``obj[key]``, with errors naming ``where.key``."""
    if key not in obj:
        raise CaptureError(path, f"missing key {key!r}", f"{where}.{key}")
    return _vectors([obj[key]], path, f"{where}.{key}")[0]


def _load_generic(cj: Path, resolution, max_photos) -> Capture:
    folder = cj.parent
    data = _read_json(cj)
    names = _get(data, "images", cj)
    if not isinstance(names, list) or not names or not all(isinstance(s, str) for s in names):
        raise CaptureError(cj, "expected a non-empty list of file names", "images")
    k_all = len(names)
    lights = _per_photo(_get(data, "lights", cj), k_all, cj, "lights")
    cam_key = "camera" if "camera" in data and "cameras" not in data else "cameras"
    cams = _per_photo(_get(data, cam_key, cj), k_all, cj, cam_key)
    # The entry each photo takes its light and camera from (one entry may serve all).
    light_of = _entry_names("lights", data["lights"], k_all)
    camera_of = _entry_names(cam_key, data[cam_key], k_all)
    side = _positive(_get(data, "side", cj), cj, "side")
    transfer = _get(data, "transfer", cj)
    k = min(k_all, max_photos) if max_photos else k_all
    files = [folder / s for s in names[:k]]
    for i, f in enumerate(files):
        if not f.is_file():
            raise CaptureError(cj, f"photo {f} does not exist", f"images[{i}]")
    kinds = {str(lt.get("type", "point")) for lt in lights}
    if not kinds <= {"point", "directional"} or len(kinds) != 1:
        raise CaptureError(
            cj, f"light types {sorted(kinds)}: use one of 'point', 'directional'", "lights"
        )
    point = kinds == {"point"}
    key, pkey = ("position", "power") if point else ("direction", "irradiance")
    geo = np.stack([_entry(lt, key, cj, f"lights[{i}]") for i, lt in enumerate(lights[:k])])
    if not point and np.any(np.linalg.norm(geo, axis=1) == 0):
        raise CaptureError(cj, "a direction is the zero vector", "lights[].direction")
    cpos = np.stack(
        [_entry(cm, "position", cj, f"{cam_key}[{i}]") for i, cm in enumerate(cams[:k])]
    )
    sat = data.get("saturation")
    if sat is not None:
        sat = _positive(sat, cj, "saturation")
    photos = Photos(files, transfer, cj, saturation=sat)
    c = photos.images.shape[-1]
    power = np.stack(
        [
            _light_power(
                _lt_get(lt, pkey, cj, i), 1, np.zeros(1, int), c, cj, f"lights[{i}].{pkey}"
            )[0]
            for i, lt in enumerate(lights[:k])
        ]
    )
    mask, mf = None, None
    if data.get("mask"):
        mf = folder / str(data["mask"])
        if not mf.is_file():
            raise CaptureError(cj, f"mask {mf} does not exist", "mask")
        m, _, _, _ = read_pixels(mf)
        if m.shape[:2] != photos.images.shape[1:3]:
            raise CaptureError(
                mf,
                f"mask is {m.shape[1]}x{m.shape[0]} but the photos are "
                f"{photos.images.shape[2]}x{photos.images.shape[1]} (WxH)",
            )
        mask = np.any(m > 0, axis=-1)
    fields = Fields(
        camera=(cj, [f"{camera_of[i]}.position" for i in range(k)]),
        light=(cj, [f"{light_of[i]}.{key}" for i in range(k)]),
        power=(cj, [f"{light_of[i]}.{pkey}" for i in range(k)]),
        mask=mf,
    )
    return _finish(
        photos,
        files,
        layout="generic",
        source=folder,
        side=side,
        camera_pos=cpos,
        light_pos=geo if point else None,
        light_dir=None if point else geo,
        light_power=power,
        fields=fields,
        unit=str(data.get("unit", "cm")),
        meta={"capture_json": str(cj)},
        mask=mask,
    )


def _detect(path: Path) -> tuple[str, Path]:
    if path.is_file():
        name = path.name.lower()
        if name == "capture.json":
            return "generic", path
        if name in ("parameters.json", "optim.json"):
            return "svbrdf-diff-renderer", path.parent
        if name in _MG_FILES:
            return "materialgan", path.parent
        raise CaptureError(path, f"not a capture file; expected one of: {_EXPECTED}")
    if not path.is_dir():
        raise CaptureError(path, "no such file or folder")
    if (path / "capture.json").is_file():
        return "generic", path / "capture.json"
    if (path / "parameters.json").is_file() or (path / "optim.json").is_file():
        return "svbrdf-diff-renderer", path
    if (path / "camera_pos.txt").is_file():
        return "materialgan", path
    raise CaptureError(path, f"no capture layout found; expected {_EXPECTED}")


def load_capture(
    path: str | Path,
    layout: str = "auto",
    resolution: int | None = None,
    max_photos: int | None = None,
) -> Capture:
    """Read a planar flash capture (module docstring for the layouts).

    Args:
        path: the capture folder, or its ``capture.json`` / ``parameters.json``.
        layout: ``"auto"`` (by the files present: capture.json, then parameters.json, then
            camera_pos.txt), ``"svbrdf-diff-renderer"``, ``"materialgan"`` or ``"generic"``.
        resolution: photo width wanted. For svbrdf-diff-renderer the folder
            ``reference/<resolution>`` if present; in every layout larger photos are
            box-downsampled (:meth:`Capture.downsample`) by an integer factor to it.
        max_photos: read only the first photos (in the layout's order).

    Returns:
        A :class:`Capture` (linear float32 images, status, geometry). Raises
        :class:`CaptureError` naming the file and field of any missing or malformed input.
    """
    path = Path(path)
    if layout == "auto":
        layout, where = _detect(path)
    elif layout not in _LAYOUTS:
        raise JaxreflError(f"unknown layout {layout!r}; use 'auto' or one of {_LAYOUTS}")
    else:
        where = path
        if layout == "generic" and path.is_dir():
            where = path / "capture.json"
        elif layout != "generic" and path.is_file():
            where = path.parent
    if max_photos is not None and max_photos < 1:
        raise JaxreflError(f"max_photos must be >= 1, got {max_photos}")
    if resolution is not None and not (isinstance(resolution, int) and resolution >= 1):
        raise CaptureError(
            path,
            f"must be a photo width in pixels (an integer >= 1), got {resolution!r}",
            "resolution",
        )
    if layout == "svbrdf-diff-renderer":
        newer = not (where / "parameters.json").is_file() and (where / "optim.json").is_file()
        cap = _load_svbrdf(
            where, resolution, max_photos, "optim.json" if newer else "parameters.json"
        )
    else:
        loader = {"generic": _load_generic, "materialgan": _load_materialgan}[layout]
        cap = loader(where, resolution, max_photos)
    w = cap.shape[2]
    if resolution is not None and resolution != w:
        if resolution < 1 or w % resolution or cap.shape[1] % (w // resolution):
            raise CaptureError(
                cap.source,
                f"photos are {w} wide; cannot box-downsample to {resolution}",
                "resolution",
            )
        cap = cap.downsample(w // resolution)
    return cap
