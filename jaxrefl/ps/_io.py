"""Photometric-stereo captures on disk: the UW psm layout and the DiLiGenT layout.

Both loaders return a :class:`PSCapture` in the frame of :mod:`jaxrefl.ps` (x right, y up,
z towards the camera; image row 0 at the top) and raise :class:`PSInputError` naming the
file and the problem (images of different sizes, a light count that does not match, a
light of zero length or below the horizon, an empty mask, 8-bit files where 16-bit ones
are expected).

**UW psm** (University of Washington CSE 455 photometric-stereo data, courtesy S. Seitz):
a folder ``OBJ/`` with ``OBJ.0.tga`` ... ``OBJ.11.tga`` and ``OBJ.mask.tga`` (8-bit RGB
TGA; Pillow honours the TGA origin flag, so rows come top first), an optional listing
``../OBJ.txt`` (the count, then the image paths, then the mask) fixing the order, and
``lights.txt`` in the folder or beside it: the count, then one unit vector per line from
the object towards the light, +z towards the camera, +y up the image (checked with the
chrome sphere: its highlight moves up the image as l_y grows). Values are taken as linear
(code / 255; the course treats them so); codes 255 (saturated) and 0 (dark) are not
usable observations.

**DiLiGenT** (Shi, Wu, Tan, Chen, Ikeuchi & Tan, "A benchmark dataset and evaluation for
non-Lambertian and uncalibrated photometric stereo", TPAMI 2019): a folder with
``filenames.txt`` (one image name per line), ``light_directions.txt`` (K lines x y z,
unit vectors towards the lights in the camera frame: x right, y up, z towards the
viewer), ``light_intensities.txt`` (K lines R G B), ``mask.png``, the images as 16-bit RGB
PNGs read at full depth (value / 65535; 65535 is saturated, 0 dark) and the ground truth
``Normal_gt.mat`` (variable ``Normal_gt``, H x W x 3, same frame; preferred, full
precision) or ``Normal_gt.png`` (RGB = (n + 1) / 2, rows top first). This is the
convention its authors document and the loaders of published methods follow (normals and
lights used as given, without flips); ``Normal_gt`` is renormalised after decoding.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from jaxrefl.io import read_png, write_png

from ._capture import PSCapture, PSInputError, check_lights
from ._mat import read_mat, write_mat

__all__ = ["load_capture", "load_diligent", "load_uw", "save_diligent"]


def _read_text(path: Path) -> str:
    """The text of a UTF-8 listing or lights file; other bytes are refused, file named."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise PSInputError(
            path, f"not a UTF-8 text file ({e.reason} at byte {e.start}); expected numbers"
        ) from None


def _read_8bit(path: Path) -> np.ndarray:
    from PIL import Image

    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file not found")
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode not in ("L", "RGB", "RGBA", "LA", "P"):
                raise PSInputError(path, f"image mode {im.mode} is not an 8-bit grey/RGB image")
            a = np.asarray(im.convert("RGB") if im.mode == "P" else im)
    except (OSError, Image.DecompressionBombError) as e:
        raise PSInputError(path, f"cannot read image: {e}") from None
    a = a[..., None] if a.ndim == 2 else a
    return a[..., :3] if a.shape[-1] in (3, 4) else a[..., :1]


def _check_size(path: Path, a: np.ndarray, first: tuple[Path, tuple[int, ...]] | None):
    if first is not None and a.shape != first[1]:
        raise PSInputError(
            path,
            f"image is {a.shape[1]}x{a.shape[0]}x{a.shape[2]} (WxHxC) but {first[0].name} is "
            f"{first[1][1]}x{first[1][0]}x{first[1][2]}; all images must have one size",
        )


def _read_lights_uw(path: Path) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: lights file not found")
    rows = [ln.split() for ln in _read_text(path).splitlines() if ln.strip()]
    try:
        count = int(rows[0][0])
        d = np.array([[float(x) for x in r] for r in rows[1:]])
    except (ValueError, IndexError):
        msg = "expected the light count, then one 'x y z' line per light"
        raise PSInputError(path, msg) from None
    if d.ndim != 2 or d.shape[1] != 3:
        raise PSInputError(path, "every light line must hold three numbers x y z")
    if count != d.shape[0]:
        raise PSInputError(path, f"the first line says {count} lights but {d.shape[0]} follow")
    return d


def _uw_files(obj: Path) -> tuple[list[Path], Path]:
    name = obj.name
    listing = obj.parent / f"{name}.txt"
    if listing.is_file():
        lines = [ln.strip() for ln in _read_text(listing).splitlines() if ln.strip()]
        try:
            count = int(lines[0])
        except (ValueError, IndexError):
            raise PSInputError(listing, "first line must be the number of images") from None
        names = [Path(s).name for s in lines[1:]]
        if len(names) < count:
            raise PSInputError(listing, f"lists {len(names)} files, the count says {count}")
        files = [obj / s for s in names[:count]]
        mask = obj / names[count] if len(names) > count else obj / f"{name}.mask.tga"
        return files, mask
    pat = re.compile(rf"{re.escape(name)}\.(\d+)\.tga$", re.IGNORECASE)
    found = sorted(
        ((int(m.group(1)), p) for p in obj.iterdir() if (m := pat.match(p.name))),
        key=lambda t: t[0],
    )
    if not found:
        raise FileNotFoundError(f"{obj}: no images named {name}.<n>.tga")
    return [p for _, p in found], obj / f"{name}.mask.tga"


def load_uw(obj_dir: str | Path, lights: str | Path | None = None) -> PSCapture:
    """Load one object of the UW psm layout (module docstring)."""
    obj = Path(obj_dir)
    if not obj.is_dir():
        raise FileNotFoundError(f"{obj}: capture folder not found")
    files, mask_path = _uw_files(obj)
    if not files:
        raise PSInputError(obj, "lists no images; photometric stereo needs at least 3")
    if lights is None:
        cands = [obj / "lights.txt", obj.parent / "lights.txt"]
        lights = next((c for c in cands if c.is_file()), cands[0])
    d = _read_lights_uw(Path(lights))
    imgs, first = [], None
    for f in files:
        a = _read_8bit(f)
        _check_size(f, a, first)
        first = first or (f, a.shape)
        imgs.append(a)
    raw = np.stack(imgs)
    m = _read_8bit(mask_path)
    if m.shape[:2] != raw.shape[1:3]:
        raise PSInputError(
            mask_path,
            f"mask is {m.shape[1]}x{m.shape[0]}, images are {raw.shape[2]}x{raw.shape[1]}",
        )
    mask = np.any(m > 127, axis=-1)
    if not mask.any():
        raise PSInputError(mask_path, "the mask is empty (no pixel above 127)")
    d, e = check_lights(d, None, raw.shape[0], raw.shape[-1], lights)
    usable = (raw > 0) & (raw < 255) & mask[None, ..., None]
    return PSCapture(
        (raw / 255.0).astype(np.float32), d, e, mask, usable, None, obj.name, obj, tuple(files), 8
    )


def _read_table(path: Path, cols: int) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        a = np.loadtxt(path, ndmin=2)
    except ValueError as e:
        raise PSInputError(path, f"expected {cols} numbers per line ({e})") from None
    if a.shape[1] != cols:
        raise PSInputError(path, f"expected {cols} numbers per line, got {a.shape[1]}")
    return a


def _read_normals_gt(root: Path, shape: tuple[int, int]) -> np.ndarray | None:
    mat, png = root / "Normal_gt.mat", root / "Normal_gt.png"
    if mat.is_file():
        arrs = read_mat(mat)
        if "Normal_gt" not in arrs:
            raise PSInputError(mat, f"no variable Normal_gt (found {sorted(arrs)})")
        n = arrs["Normal_gt"]
        where = mat
    elif png.is_file():
        a, bits = read_png(png)
        n = a[..., :3].astype(np.float64) / (2**bits - 1) * 2.0 - 1.0
        where = png
    else:
        return None
    if n.shape != (*shape, 3):
        raise PSInputError(where, f"normals are {n.shape}, images are {shape}")
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(norm > 0.5, n / np.where(norm > 0, norm, 1.0), np.nan)


def load_diligent(root: str | Path, require_16bit: bool = True) -> PSCapture:
    """Load one object in the DiLiGenT layout (module docstring). ``require_16bit=False``
    accepts 8-bit PNGs (value / 255) instead of refusing them."""
    root = Path(root)
    listing = root / "filenames.txt"
    if not listing.is_file():
        raise FileNotFoundError(f"{listing}: not found (DiLiGenT layout)")
    files = [root / ln.strip() for ln in _read_text(listing).splitlines() if ln.strip()]
    if not files:
        raise PSInputError(listing, "lists no images")
    dirs = _read_table(root / "light_directions.txt", 3)
    ints = _read_table(root / "light_intensities.txt", 3)
    imgs: list[np.ndarray] = []
    first: tuple[Path, tuple[int, ...]] | None = None
    depth = 16
    for f in files:
        if not f.is_file():
            raise FileNotFoundError(f"{f}: image listed in filenames.txt not found")
        a, bits = read_png(f)
        a = a[..., :3] if a.shape[-1] in (3, 4) else a[..., :1]
        if require_16bit and bits != 16:
            raise PSInputError(
                f,
                f"{bits}-bit PNG where DiLiGenT images are 16-bit; the low bits are lost "
                "(re-export at 16 bits, or pass require_16bit=False)",
            )
        if first is not None and bits != depth:
            raise PSInputError(f, f"{bits}-bit image but {first[0].name} is {depth}-bit")
        _check_size(f, a, first)
        first, depth = first or (f, a.shape), bits
        imgs.append(a)
    raw = np.stack(imgs)
    top = 2**depth - 1
    mpath = root / "mask.png"
    if not mpath.is_file():
        raise FileNotFoundError(f"{mpath}: mask not found")
    m, _ = read_png(mpath)
    if m.shape[:2] != raw.shape[1:3]:
        raise PSInputError(
            mpath, f"mask is {m.shape[1]}x{m.shape[0]}, images are {raw.shape[2]}x{raw.shape[1]}"
        )
    mask = np.any(m[..., : min(3, m.shape[-1])] > 0, axis=-1)
    if not mask.any():
        raise PSInputError(mpath, "the mask is empty (every pixel 0)")
    d, e = check_lights(
        dirs,
        ints,
        raw.shape[0],
        raw.shape[-1],
        root / "light_directions.txt",
        root / "light_intensities.txt",
    )
    usable = (raw > 0) & (raw < top) & mask[None, ..., None]
    gt = _read_normals_gt(root, raw.shape[1:3])
    images = (raw / float(top)).astype(np.float32)
    return PSCapture(images, d, e, mask, usable, gt, root.name, root, tuple(files), depth)


def load_capture(path: str | Path) -> PSCapture:
    """DiLiGenT if the folder has ``filenames.txt``, else UW psm."""
    p = Path(path)
    if not p.is_dir():
        raise FileNotFoundError(f"{p}: capture folder not found")
    if (p / "filenames.txt").is_file():
        return load_diligent(p)
    return load_uw(p)


def save_diligent(
    root: str | Path,
    images: np.ndarray,
    lights: np.ndarray,
    intensities: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray | None = None,
    bits: int = 16,
    normal_format: str = "both",
) -> Path:
    """Write a capture in the DiLiGenT layout: ``images`` (K, H, W, 3) linear in [0, 1]
    (clipped, rounded to ``bits``), ``normal_format`` "png", "mat" or "both"."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    top = 2**bits - 1
    dtype = np.uint16 if bits == 16 else np.uint8
    names = []
    for k, img in enumerate(np.asarray(images)):
        name = f"{k + 1:03d}.png"
        write_png(root / name, np.round(np.clip(img, 0.0, 1.0) * top).astype(dtype))
        names.append(name)
    (root / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(root / "light_directions.txt", np.asarray(lights), fmt="%.8f")
    np.savetxt(root / "light_intensities.txt", np.asarray(intensities), fmt="%.8f")
    write_png(root / "mask.png", (np.asarray(mask, bool) * 255).astype(np.uint8))
    if normals is not None:
        n = np.nan_to_num(np.asarray(normals, np.float64))
        if normal_format in ("png", "both"):
            write_png(root / "Normal_gt.png", np.round((n + 1) / 2 * 65535).astype(np.uint16))
        if normal_format in ("mat", "both"):
            write_mat(root / "Normal_gt.mat", {"Normal_gt": n})
    return root
