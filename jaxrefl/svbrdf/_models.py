"""The models a capture can be fitted with, by name, and their parameter spaces.

=============  ============================================================================
name            model (``jaxrefl.brdf``) and free parameters per pixel
=============  ============================================================================
``ggx``         Cook–Torrance, GGX distribution, height-correlated Smith shadowing, Schlick
                Fresnel, on a Lambertian base: diffuse ``albedo`` (RGB), ``specular`` F0
                (grey: one value shared by R, G, B) and ``alpha`` (GGX width; the maps
                also give perceptual ``roughness`` = sqrt(alpha)). The default.
``beckmann``    the same with the Beckmann distribution
``ggx_rgb``     ``ggx`` with a coloured specular F0 (metals): 7 parameters
``lambert``     Lambertian ``albedo`` (RGB) only: the diffuse-only baseline
=============  ============================================================================
"""

from __future__ import annotations

from jaxrefl import brdf
from jaxrefl.fit import ParamSpace

__all__ = ["CAPTURE_MODELS", "capture_model"]

CAPTURE_MODELS: dict[str, str] = {
    "ggx": "Cook-Torrance GGX + Lambert, grey specular F0 (albedo RGB, specular, alpha)",
    "beckmann": "Cook-Torrance Beckmann + Lambert, grey specular F0",
    "ggx_rgb": "Cook-Torrance GGX + Lambert, coloured specular F0",
    "lambert": "Lambertian albedo only (diffuse baseline)",
}


def capture_model(name: str, channels: int = 3) -> tuple[brdf.BRDF, ParamSpace]:
    """(model, parameter space) of a capture model named in :data:`CAPTURE_MODELS`."""
    if name == "lambert":
        m = brdf.get("lambert")
        return m, ParamSpace(m, channels=channels)
    if name in ("ggx", "beckmann", "ggx_rgb"):
        m = brdf.get(
            "cook_torrance",
            distribution="beckmann" if name == "beckmann" else "ggx",
            shadowing="smith_height_correlated",
            fresnel="schlick",
            diffuse="lambert",
        )
        grey = () if name == "ggx_rgb" else ("specular",)
        return m, ParamSpace(m, channels=channels, grey=grey)
    raise ValueError(f"unknown capture model {name!r}; choose from {', '.join(CAPTURE_MODELS)}")
