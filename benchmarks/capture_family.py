"""A family of synthetic flash captures that vary what users' captures vary.

Each member is a planar sample of side ``side_cm`` (11.136 cm, MaterialGAN's ``bath_tile``)
photographed ``photos`` times by a phone held about 24 cm above it, rendered with the
project's renderer (:func:`jaxrefl.scene.render`) and the fit's own material model
(``jaxrefl.svbrdf.capture_model("ggx_rgb")``: Cook–Torrance, GGX, height-correlated Smith,
Schlick Fresnel, on a Lambertian base); radiance = light_power f_r cos(theta_i) / r^2 with
no vignetting, the convention of the real flash captures (:mod:`jaxrefl.demo`).

What varies between members (:class:`FamilyMember`):

* the GGX width ``alpha`` over the map, log-spaced between ``alpha_range``;
* the specular F0: grey (a dielectric, ``f0`` range) or a coloured metal (``metal``: its
  RGB F0, on a share ``metal_cover`` of the surface, with a low diffuse albedo there);
* the flash offset from the lens, ``flash_offset_cm`` (the true light position; the files
  a user's layout holds say the flash sits at the lens: :func:`write_member`);
* the noise level, ``noise`` (Gaussian, std ``noise`` x value + ``NOISE_FLOOR`` x ``noise``
  of full scale, the proportions of ``jaxrefl demo``), then the camera's range [0, 1];
* the photo count and the image size;
* the maps: smooth random fields (sums of low-frequency waves, the same material at every
  ``size``), optionally with ``tiles`` x ``tiles`` patches as in the demo; RGB albedo.

:data:`FAMILY`, what each member stands for:

=====================  ================================================================
``mirror_plastic``     glossy lacquer, near-mirror (alpha 0.02-0.1), grey F0 0.04,
                       flash 0.5 cm from the lens, 1% noise, 9 photos, 128 px
``rough_dielectric``   matte stone/paper (alpha 0.3-0.7), F0 0.04, flash 1.5 cm away,
                       3% noise, 5 photos, 64 px: few, noisy photos of a dull surface
``grey_gloss``         a user's glossy capture: alpha 0.2-0.7 (roughness 0.45-0.84),
                       grey F0 0.04-0.5, flash 1 cm away, 1% noise, 9 photos, 256 px
``gold_foil``          a coloured metal everywhere (RGB F0 up to 0.9, albedo 0.03),
                       alpha 0.05-0.3, flash 1 cm away, 0.5% noise, 12 photos, 128 px,
                       power 300 (exposed for the highlights, as a user would)
``copper_inlay``       copper on half of a tiled dielectric (4 x 4 patches plus smooth
                       variation), alpha 0.1-0.5, flash 0.8 cm, 2% noise, 16 photos, 128 px,
                       power 600
``dim_many``           a dark, underexposed capture (power 500): alpha 0.1-0.6, F0
                       0.02-0.08, dark albedo, flash 1.2 cm, 3% noise, 16 photos, 64 px
``colocated_tiles``    the demo's kind of sample (4 x 4 tiles, alpha 0.09-0.56, F0
                       0.02-0.12) with the flash at the lens, 1% noise, 9 photos, 128 px:
                       the control on which the model's geometry holds
=====================  ================================================================

:func:`render_member` gives the photos, geometry and true maps (:class:`RenderedMember`);
:func:`write_member` writes them in one of the layouts :func:`jaxrefl.io.load_capture`
reads, with ``truth.npz`` (maps in the fit's conventions: ``albedo`` (H, W, 3) diffuse,
``specular`` (H, W, 3) Schlick F0, ``alpha`` (H, W) GGX width, ``roughness`` = sqrt(alpha),
``metal`` (H, W) metal share; ``light_pos`` the TRUE flash positions, ``camera_pos``,
``light_power``) and ``member.json``. Deterministic given the member's ``seed``.

    python benchmarks/capture_family.py --out DIR [--layouts generic,materialgan,...]
        [--members a,b] [--size N] [--true-light]

writes ``DIR/<member>/<layout>/`` for every member and layout.

:func:`demo_rig_capture` is the synthetic capture of ``benchmarks/predictive_coverage.py``
(the demo's rig photographing random maps, in memory).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "FAMILY",
    "LAYOUTS",
    "FamilyMember",
    "RenderedMember",
    "demo_rig_capture",
    "render_member",
    "write_member",
]

SIDE_CM = 11.136  # the imaged square, as the demo and bath_tile
GAMMA = 2.2  # the public layouts' 8-bit encoding, value^(1/2.2) (Guo et al. 2020)
# Noise floor (full-scale units) as a share of the relative noise: 0.2% for 1%, the
# proportions of `jaxrefl demo`'s sensor noise.
NOISE_FLOOR = 0.2
METAL_ALBEDO = 0.03  # a metal's diffuse albedo: a little dust and oxide, no subsurface
LAYOUTS = ("generic", "svbrdf-diff-renderer", "materialgan")
# The reference grid on which each smooth field is scaled to [0, 1]: the same for every
# image size, so that a member is one material at any size.
_REF = 129


@dataclass(frozen=True)
class FamilyMember:
    """One synthetic capture's specification (module docstring).

    ``alpha_range``: the GGX width's min and max over the map; ``f0``: the grey
    (dielectric) F0's; ``metal``: RGB F0 of a coloured metal covering a share
    ``metal_cover`` of the surface (None: no metal); ``albedo_range``: diffuse albedo per
    channel; ``flash_offset_cm``: distance from the lens to the flash, in the plane of the
    phone; ``noise``: relative noise std; ``tiles``: patches per side (0: smooth maps only);
    ``light_power``: the flash's radiant intensity (the real captures: 1500);
    ``photo_gain_spread``: each photo's flash output times exposure is ``light_power`` times
    a gain drawn uniformly in [1 - spread, 1 + spread] and divided by the gains' geometric
    mean (the files state ``light_power`` for every photo; the truth keeps the gains).
    """

    name: str
    alpha_range: tuple[float, float]
    f0: tuple[float, float] = (0.04, 0.04)
    metal: tuple[float, float, float] | None = None
    metal_cover: float = 1.0
    albedo_range: tuple[float, float] = (0.05, 0.8)
    flash_offset_cm: float = 0.0
    noise: float = 0.01
    photos: int = 9
    size: int = 128
    tiles: int = 0
    light_power: float = 1500.0
    side_cm: float = SIDE_CM
    seed: int = 0
    photo_gain_spread: float = 0.0

    def __post_init__(self) -> None:
        lo, hi = self.alpha_range
        if not 0.0 < lo <= hi <= 1.0:
            raise ValueError(f"{self.name}: alpha_range must satisfy 0 < lo <= hi <= 1")
        if not 0.0 <= self.f0[0] <= self.f0[1] <= 1.0:
            raise ValueError(f"{self.name}: f0 must satisfy 0 <= lo <= hi <= 1")
        if self.photos < 1 or self.size < 1 or self.noise < 0 or self.flash_offset_cm < 0:
            raise ValueError(f"{self.name}: photos, size >= 1; noise, flash offset >= 0")
        if not 0.0 <= self.photo_gain_spread < 1.0:
            raise ValueError(f"{self.name}: photo_gain_spread must be in [0, 1)")


FAMILY: list[FamilyMember] = [
    FamilyMember("mirror_plastic", (0.02, 0.1), flash_offset_cm=0.5, noise=0.01, photos=9, seed=1),
    FamilyMember(
        "rough_dielectric",
        (0.3, 0.7),
        flash_offset_cm=1.5,
        noise=0.03,
        photos=5,
        size=64,
        seed=2,
    ),
    FamilyMember(
        "grey_gloss",
        (0.2, 0.7),
        f0=(0.04, 0.5),
        flash_offset_cm=1.0,
        noise=0.01,
        photos=9,
        size=256,
        seed=3,
    ),
    FamilyMember(
        "gold_foil",
        (0.05, 0.3),
        metal=(0.9, 0.7, 0.35),
        flash_offset_cm=1.0,
        noise=0.005,
        photos=12,
        light_power=300.0,
        seed=4,
    ),
    FamilyMember(
        "copper_inlay",
        (0.1, 0.5),
        metal=(0.85, 0.55, 0.45),
        metal_cover=0.5,
        flash_offset_cm=0.8,
        noise=0.02,
        photos=16,
        tiles=4,
        light_power=600.0,
        seed=5,
    ),
    FamilyMember(
        "dim_many",
        (0.1, 0.6),
        f0=(0.02, 0.08),
        albedo_range=(0.03, 0.4),
        flash_offset_cm=1.2,
        noise=0.03,
        photos=16,
        size=64,
        light_power=500.0,
        seed=6,
    ),
    FamilyMember("colocated_tiles", (0.09, 0.56), f0=(0.02, 0.12), photos=9, tiles=4, seed=7),
]


# ----------------------------------------------------------------------------- maps
def _field(rng: np.random.Generator, tiles: int):
    """A random smooth function of (u, v) in [0, 1]^2 scaled to [0, 1] on the reference
    grid: a sum of 5 waves of 0.5 to 2 cycles per side (amplitude falling as 1/frequency),
    plus as much again of piecewise-constant patches when ``tiles`` > 0."""
    freq = rng.uniform(0.5, 2.0, 5) * np.exp(1j * rng.uniform(0, 2 * np.pi, 5))
    phase = rng.uniform(0, 2 * np.pi, 5)
    amp = 1.0 / np.abs(freq)
    patch = rng.uniform(0.0, 1.0, (tiles, tiles)) if tiles else None

    def raw(u, v):
        w = sum(
            a * np.cos(2 * np.pi * (f.real * u + f.imag * v) + p)
            for a, f, p in zip(amp, freq, phase, strict=True)
        )
        w = w / amp.sum()  # in [-1, 1]
        if patch is not None:
            i = np.minimum((v * tiles).astype(int), tiles - 1)
            j = np.minimum((u * tiles).astype(int), tiles - 1)
            w = w + (2 * patch[i, j] - 1)
        return w

    g = (np.arange(_REF) + 0.5) / _REF
    ref = raw(*np.meshgrid(g, g))
    lo, hi = float(ref.min()), float(ref.max())
    return lambda u, v: np.clip((raw(u, v) - lo) / (hi - lo), 0.0, 1.0), ref


def _maps(m: FamilyMember, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The true maps at pixel centres: albedo, specular (RGB F0), alpha, metal share."""
    c = (np.arange(m.size) + 0.5) / m.size
    u, v = np.meshgrid(c, c)  # u along columns (x), v along rows (down the image)
    t_alpha, _ = _field(rng, m.tiles)
    t_f0, _ = _field(rng, m.tiles)
    t_alb = [_field(rng, m.tiles)[0] for _ in range(3)]
    t_metal, ref_metal = _field(rng, m.tiles)
    lo, hi = m.alpha_range
    alpha = lo * (hi / lo) ** t_alpha(u, v)  # log-spaced: as many near-mirror as rough pixels
    tf = t_f0(u, v)
    grey = m.f0[0] + (m.f0[1] - m.f0[0]) * tf
    a_lo, a_hi = m.albedo_range
    albedo = np.stack([a_lo + (a_hi - a_lo) * t(u, v) for t in t_alb], -1)
    if m.metal is None:
        metal = np.zeros_like(alpha)
    elif m.metal_cover >= 1.0:
        metal = np.ones_like(alpha)
    else:
        # metal where the field is in its top `metal_cover` share, with borders of mixed
        # pixels 0.1 of the field's range wide (a real inlay's edge is not pixel-sharp)
        thr = float(np.quantile(ref_metal, 1.0 - m.metal_cover))
        lo_m, hi_m = float(ref_metal.min()), float(ref_metal.max())
        tm = (thr - lo_m) / (hi_m - lo_m)
        metal = np.clip((t_metal(u, v) - tm) / 0.1 + 0.5, 0.0, 1.0)
    # the metal's F0 varies by up to 20% with the F0 field (tarnish, polish)
    metal_f0 = np.asarray(m.metal or (0.0, 0.0, 0.0)) * (0.8 + 0.2 * tf[..., None])
    mk = metal[..., None]
    return {
        "albedo": (1 - mk) * albedo + mk * METAL_ALBEDO,
        "specular": (1 - mk) * grey[..., None] + mk * metal_f0,
        "alpha": alpha,
        "roughness": np.sqrt(alpha),
        "metal": metal,
    }


# ----------------------------------------------------------------------------- rig
def _rig(m: FamilyMember, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(camera_pos, light_pos), (K, 3) cm: the phone over a disc of radius 4.5 cm centred
    near the sample's centre (a sunflower spiral, as spread as the demo's nine positions),
    22.8-24.7 cm up; the flash ``flash_offset_cm`` from the lens in one direction of the
    horizontal plane (the phone held the same way for every photo)."""
    k = m.photos
    r = 4.5 * np.sqrt((np.arange(k) + 0.5) / k)
    phi = np.arange(k) * np.pi * (3 - np.sqrt(5)) + rng.uniform(0, 2 * np.pi)
    xy = np.stack([1.2 + r * np.cos(phi), 0.3 + r * np.sin(phi)], -1)
    cams = np.concatenate([xy, rng.uniform(22.8, 24.7, (k, 1))], -1)
    d = rng.uniform(0, 2 * np.pi)
    lights = cams + m.flash_offset_cm * np.array([np.cos(d), np.sin(d), 0.0])
    return cams, lights


@dataclass
class RenderedMember:
    """A rendered member: ``images`` (K, H, W, 3) what the camera recorded (linear, noisy,
    clipped to [0, 1]), ``radiance`` the noiseless unclipped radiance, the geometry (cm:
    ``camera_pos``, TRUE ``light_pos``, ``light_power`` (K, 3) as the files state it) and
    ``truth`` (the maps of the module docstring); ``photo_gain`` (K,) the true gain of each
    photo over ``light_power`` (1 unless the member's ``photo_gain_spread``)."""

    member: FamilyMember
    images: np.ndarray
    radiance: np.ndarray
    camera_pos: np.ndarray
    light_pos: np.ndarray
    light_power: np.ndarray
    truth: dict[str, np.ndarray]
    photo_gain: np.ndarray | None = None

    def with_noise(self, seed: int) -> RenderedMember:
        """The same photos with the noise drawn again from ``seed`` (repeated-draw checks)."""
        m = self.member
        rng = np.random.default_rng(seed)
        rad = self.radiance.astype(np.float64)
        std = m.noise * (rad + NOISE_FLOOR)
        images = np.clip(rad + std * rng.standard_normal(rad.shape), 0.0, 1.0)
        return dataclasses.replace(self, images=images.astype(np.float32))

    def written_light_pos(self, true_light: bool = False) -> np.ndarray:
        """The flash positions a capture's files give: at the lens unless ``true_light``."""
        return self.light_pos if true_light else self.camera_pos

    def capture(self, true_light: bool = False):
        """The in-memory :class:`jaxrefl.io.Capture` (linear images; values at the camera's
        full scale marked saturated), the flash at the lens unless ``true_light``."""
        from jaxrefl.io import Capture, ObsStatus
        from jaxrefl.scene import planar_points

        m = self.member
        status = np.where(self.images >= 1.0, ObsStatus.SATURATED, ObsStatus.OK)
        return Capture(
            images=self.images,
            status=status.astype(np.uint8),
            light_pos=self.written_light_pos(true_light),
            light_dir=None,
            light_power=self.light_power,
            camera_pos=self.camera_pos,
            side=m.side_cm,
            points=np.asarray(planar_points(m.size, m.size, m.side_cm), np.float64),
            saturation_level=1.0,
        )


def render_member(member: FamilyMember) -> RenderedMember:
    """Render ``member``'s photos (module docstring), deterministic given its seed."""
    import jax.numpy as jnp

    from jaxrefl.scene import PinholeCamera, PointLight, planar_points, render
    from jaxrefl.svbrdf import capture_model

    m = member
    rng = np.random.default_rng(m.seed)
    truth = _maps(m, rng)
    cams, lights = _rig(m, rng)
    model, _space = capture_model("ggx_rgb")
    params = {n: jnp.asarray(truth[n]) for n in model.param_names}
    power = np.full((m.photos, 3), m.light_power)
    gain = np.ones(m.photos)
    if m.photo_gain_spread > 0:
        # drawn after the maps and the rig, so a member without a spread is unchanged
        gain = rng.uniform(1 - m.photo_gain_spread, 1 + m.photo_gain_spread, m.photos)
        gain = gain / np.exp(np.mean(np.log(gain)))
    radiance = render(
        model,
        params,
        [PointLight(p, e * g) for p, e, g in zip(lights, power, gain, strict=True)],
        [PinholeCamera(p) for p in cams],
        points=planar_points(m.size, m.size, m.side_cm),
        cos4=False,  # the flash captures carry no vignetting
    )
    radiance = np.asarray(radiance, np.float64)
    std = m.noise * (radiance + NOISE_FLOOR)
    images = np.clip(radiance + std * rng.standard_normal(radiance.shape), 0.0, 1.0)
    return RenderedMember(
        member=m,
        images=images.astype(np.float32),
        radiance=radiance.astype(np.float32),
        camera_pos=cams,
        light_pos=lights,
        light_power=power,
        truth=truth,
        photo_gain=gain,
    )


# ----------------------------------------------------------------------------- writing
def _encode8(images: np.ndarray) -> np.ndarray:
    """8-bit codes of the public layouts: round(value^(1/2.2) * 255), clipped to [0, 1]."""
    return np.rint(np.clip(images, 0.0, 1.0) ** (1 / GAMMA) * 255).astype(np.uint8)


def _save_pngs(folder: Path, images: np.ndarray) -> None:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for i, q in enumerate(_encode8(images)):
        Image.fromarray(q).save(folder / f"{i:02d}.png")


def _write_svbrdf(r: RenderedMember, folder: Path, lights: np.ndarray) -> None:
    m = r.member
    _save_pngs(folder / "images" / "reference" / str(m.size), r.images)
    params = {
        "_comment": f"capture_family member {m.name}; in cm; svbrdf-diff-renderer layout",
        "images_dir": "images",
        "image_size": m.side_cm,
        "idx": list(range(m.photos)),
        "camera_pos": r.camera_pos.tolist(),
        "light_pos": lights.tolist(),
        "light_pow": [m.light_power] * 3,  # one per channel, as the real captures
        "gamma": GAMMA,
    }
    (folder / "parameters.json").write_text(json.dumps(params, indent=2))


def _write_materialgan(r: RenderedMember, folder: Path, lights: np.ndarray) -> None:
    _save_pngs(folder, r.images)
    fmt = "%.17g"
    np.savetxt(folder / "camera_pos.txt", r.camera_pos, delimiter=",", fmt=fmt)
    np.savetxt(folder / "light_pos.txt", lights, delimiter=",", fmt=fmt)
    np.savetxt(folder / "light_power.txt", r.light_power[:1], delimiter=",", fmt=fmt)
    (folder / "image_size.txt").write_text(f"{r.member.side_cm!r}\n")


def write_member(
    member: FamilyMember | RenderedMember,
    folder: str | Path,
    layout: str = "generic",
    *,
    true_light: bool = False,
    file_format: str = "exr",
) -> Path:
    """Write a member's capture to ``folder`` in ``layout`` (one of :data:`LAYOUTS`), with
    ``truth.npz`` and ``member.json`` beside it; returns ``folder``.

    The cameras are the true ones. The flash positions written are what a user's files
    say, the flash at the lens (each layout's light position = its camera position), or
    with ``true_light`` the true, offset ones. ``generic``: linear images in
    ``file_format`` (``"exr"``, float32, exact; or ``"png16"``/``"png8"``) with saturation
    at the camera's full scale 1; the two public layouts: 8-bit PNG, value^(1/2.2).
    """
    from jaxrefl.io import save_generic_capture

    r = member if isinstance(member, RenderedMember) else render_member(member)
    m = r.member
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lights = r.written_light_pos(true_light)
    if layout == "generic":
        save_generic_capture(
            folder,
            r.images,
            side=m.side_cm,
            light_power=r.light_power,
            camera_pos=r.camera_pos,
            light_pos=lights,
            file_format=file_format,
            saturation=1.0,
        )
    elif layout == "svbrdf-diff-renderer":
        _write_svbrdf(r, folder, lights)
    elif layout == "materialgan":
        _write_materialgan(r, folder, lights)
    else:
        raise ValueError(f"unknown layout {layout!r}; use one of {LAYOUTS}")
    arrays = {
        **r.truth,
        "light_pos": r.light_pos,
        "camera_pos": r.camera_pos,
        "light_power": r.light_power,
        "photo_gain": np.ones(m.photos) if r.photo_gain is None else r.photo_gain,
    }
    np.savez_compressed(folder / "truth.npz", **arrays)  # type: ignore[arg-type]
    spec = {
        **dataclasses.asdict(m),
        "layout": layout,
        "light_pos_written": "true" if true_light else "at the lens (camera_pos)",
        "model": "ggx_rgb: cook_torrance(ggx, smith_height_correlated, schlick) + lambert",
    }
    (folder / "member.json").write_text(json.dumps(spec, indent=2))
    return folder


# ----------------------------------------------------------------------------- demo rig
def demo_rig_capture(size: int, sigma: float, seed: int = 0):
    """(capture, truth): the demo's rig (:func:`jaxrefl.demo.demo_scene`, flash at the lens)
    photographing random maps, GGX + Lambert, albedo U(0.05, 0.8) per channel, grey F0
    U(0, 0.5), alpha = r^2 with r U(0.2, 0.8), i.i.d. per pixel; linear radiance plus
    Gaussian noise of std ``sigma`` (:func:`jaxrefl.demo.photograph_maps`)."""
    from jaxrefl.demo import demo_scene, photograph_maps

    scene = demo_scene(size=size)
    rng = np.random.default_rng(seed)
    f0 = rng.uniform(0.0, 0.5, (size, size))
    truth = {
        "albedo": rng.uniform(0.05, 0.8, (size, size, 3)),
        "specular": np.repeat(f0[..., None], 3, -1),
        "alpha": rng.uniform(0.2, 0.8, (size, size)) ** 2,
    }
    return photograph_maps(scene, truth, sigma, rng), truth


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--layouts", default=",".join(LAYOUTS), help="comma-separated layouts")
    ap.add_argument("--members", default="", help="comma-separated names (default: all)")
    ap.add_argument("--size", type=int, default=0, help="override every member's size")
    ap.add_argument(
        "--true-light", action="store_true", help="write the true (offset) flash positions"
    )
    args = ap.parse_args(argv)
    layouts = [s for s in args.layouts.split(",") if s]
    names = {s for s in args.members.split(",") if s}
    unknown = names - {m.name for m in FAMILY} | set(layouts) - set(LAYOUTS)
    if unknown:
        ap.error(f"unknown member or layout: {sorted(unknown)}")
    for m in FAMILY:
        if names and m.name not in names:
            continue
        if args.size:
            m = dataclasses.replace(m, size=args.size)
        r = render_member(m)
        sat = float(np.mean(r.images >= 1.0))
        for layout in layouts:
            write_member(r, args.out / m.name / layout, layout, true_light=args.true_light)
        print(
            f"{m.name}: {m.photos} photos, {m.size} x {m.size}, alpha {m.alpha_range}, "
            f"flash {m.flash_offset_cm} cm from the lens, noise {m.noise:.1%}, "
            f"saturated {sat:.2%} -> {args.out / m.name}/{{{','.join(layouts)}}}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
