"""The embedded demo: a procedural planar SVBRDF photographed under a phone flash.

Nothing is downloaded or shipped: the sample is generated from a seed. It is a square tile
of side 11.136 cm (the size of the MaterialGAN ``bath_tile`` example) made of 4 x 4 patches,
each with its own diffuse albedo (RGB), specular F0 (grey) and GGX roughness, plus a smooth
roughness gradient inside each patch, so that a fit has highlights to find and places
where no highlight was observed. Nine photos are taken with the flash co-located with the
camera, about 24 cm above the sample at positions like those of the real capture, and
encoded like the real photos: value^(1/2.2), clipped to [0, 1].

Model: Cook–Torrance with GGX, height-correlated Smith shadowing and Schlick Fresnel on a
Lambertian base (``jaxrefl.brdf.get("cook_torrance", diffuse="lambert")``); radiance
= light_power * f_r * cos θ_i / r^2, with no vignetting: the convention of the real flash
captures (MaterialGAN, Guo et al. 2020; :mod:`jaxrefl.io._capture`), so the written capture
reads back like a real one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import brdf
from .scene import GammaResponse, PinholeCamera, PointLight, planar_points, render

__all__ = [
    "DemoScene",
    "demo_capture",
    "demo_model",
    "demo_scene",
    "photograph_maps",
    "render_demo",
]

SIDE_CM = 11.136
LIGHT_POWER = 1500.0


@dataclass
class DemoScene:
    model: brdf.BRDF
    params: dict[str, Array]
    points: Float[Array, "H W 3"]
    positions: Float[np.ndarray, "K 3"]  # co-located camera and flash, cm
    light_power: float
    side_cm: float
    gamma: float = 2.2
    meta: dict = field(default_factory=dict)

    @property
    def lights(self) -> list[PointLight]:
        return [PointLight(p, jnp.full((3,), self.light_power)) for p in self.positions]

    @property
    def cameras(self) -> list[PinholeCamera]:
        # The phone looks at the sample centre from the flash position.
        return [PinholeCamera(p, look_at=(0.0, 0.0, 0.0)) for p in self.positions]


def demo_model() -> brdf.BRDF:
    """The demo's BRDF: GGX Cook-Torrance (height-correlated Smith, Schlick) on Lambert."""
    return brdf.get(
        "cook_torrance",
        distribution="ggx",
        shadowing="smith_height_correlated",
        fresnel="schlick",
        diffuse="lambert",
    )


def demo_scene(size: int = 128, seed: int = 0, dtype=jnp.float32) -> DemoScene:
    """Build the demo SVBRDF (``size`` x ``size`` pixels) and its nine-photo flash rig."""
    rng = np.random.default_rng(seed)
    n = 4
    patch_albedo = rng.uniform(0.05, 0.8, size=(n, n, 3))
    patch_spec = rng.uniform(0.02, 0.12, size=(n, n))
    patch_rough = rng.uniform(0.3, 0.75, size=(n, n))  # perceptual roughness, alpha = r^2
    idx = (np.arange(size) * n) // size
    rows, cols = np.meshgrid(idx, idx, indexing="ij")
    u = (np.arange(size) % (size // n)) / (size // n)  # position inside a patch, 0..1
    ramp = 0.75 + 0.5 * u[None, :]  # roughness varies by +-25% across each patch
    rough = np.clip(patch_rough[rows, cols] * ramp, 0.05, 0.95)
    params = {
        "albedo": jnp.asarray(patch_albedo[rows, cols], dtype=dtype),
        "specular": jnp.asarray(np.repeat(patch_spec[rows, cols][..., None], 3, -1), dtype=dtype),
        "alpha": jnp.asarray(rough**2, dtype=dtype),
    }
    model = demo_model()
    # Flash positions like the bath_tile capture: ~24 cm up, offsets of a few cm.
    offsets = np.array(
        [
            [2.3, 0.0],
            [4.9, 3.3],
            [-0.3, -2.3],
            [-2.8, 1.9],
            [5.2, -2.7],
            [2.5, 3.3],
            [2.9, -2.4],
            [-0.4, 0.0],
            [4.8, -0.3],
        ]
    )
    heights = np.array([24.3, 22.8, 23.9, 23.4, 23.7, 22.8, 24.1, 24.7, 24.1])
    positions = np.concatenate([offsets, heights[:, None]], axis=1)
    points = planar_points(size, size, SIDE_CM, dtype=dtype)
    return DemoScene(
        model=model,
        params=params,
        points=points,
        positions=positions,
        light_power=LIGHT_POWER,
        side_cm=SIDE_CM,
        meta={"seed": seed, "size": size, "roughness_convention": "alpha = roughness^2"},
    )


def render_demo(scene: DemoScene, encode: bool = True) -> Float[Array, "K H W 3"]:
    """Render the nine photos; encoded with value^(1/2.2) and clipped when ``encode``."""
    response = GammaResponse(gamma=scene.gamma) if encode else None
    return render(
        scene.model,
        scene.params,
        scene.lights,
        scene.cameras,
        points=scene.points,
        response=response,
        cos4=False,  # the svbrdf-diff-renderer captures carry no vignetting
    )


def demo_capture(scene: DemoScene, images: Float[np.ndarray, "K H W 3"]):
    """A :class:`jaxrefl.io.Capture` of ``scene``'s geometry (flash and camera positions,
    light power, sample points) holding ``images``: (K, H, W, 3) linear radiance such as
    ``render_demo(scene, encode=False)`` with noise added. The in-memory twin of the folder
    ``jaxrefl demo`` writes, without its 8-bit encoding; every observation is usable."""
    from .io import Capture

    images = np.asarray(images)
    k = images.shape[0]
    return Capture(
        images=images,
        status=np.zeros(images.shape, np.uint8),
        light_pos=scene.positions,
        light_dir=None,
        light_power=np.full((k, 3), scene.light_power),
        camera_pos=scene.positions,
        side=scene.side_cm,
        points=np.asarray(scene.points, np.float64),
    )


def photograph_maps(
    scene: DemoScene,
    params: dict[str, np.ndarray],
    sigma: float = 0.0,
    rng: np.random.Generator | None = None,
):
    """A :func:`demo_capture` of the demo rig photographing other parameter maps: ``params``
    (natural units, (H, W, ...) arrays keyed by ``scene.model.param_names``, H x W the
    scene's size) rendered as linear radiance L = f_r E cos(theta_i) (no encoding, no
    clipping), plus independent Gaussian noise of std ``sigma`` drawn from ``rng``. For
    synthetic captures with a known truth (coverage and calibration checks)."""
    k = len(scene.positions)
    h, w = np.shape(scene.points)[:2]
    cap = demo_capture(scene, np.zeros((k, h, w, 3), np.float32))
    geo = cap.per_pixel_geometry(dtype=np.float64)
    p = {n: jnp.asarray(v) for n, v in params.items()}
    f = np.asarray(scene.model.eval(p, jnp.asarray(geo["wi"]), jnp.asarray(geo["wo"])))
    img = f * geo["irradiance"] * geo["cos_i"][..., None]
    if sigma > 0:
        img = img + sigma * (rng or np.random.default_rng()).standard_normal(img.shape)
    return dataclasses.replace(cap, images=img.astype(np.float32))
