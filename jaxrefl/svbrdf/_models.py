"""The models a capture can be fitted with, by name, and their parameter spaces.

=============  ============================================================================
name            model (``jaxrefl.brdf``) and free parameters per pixel
=============  ============================================================================
``ggx``         Cook–Torrance, GGX distribution, height-correlated Smith shadowing, Schlick
                Fresnel, on a Lambertian base: diffuse ``albedo`` (RGB), ``specular`` F0
                (grey: one value shared by R, G, B; a dielectric's, in [0, 0.25]) and
                ``alpha`` (GGX width in [1e-3, 1]; the maps also give perceptual
                ``roughness`` = sqrt(alpha)). The default.
``beckmann``    the same with the Beckmann distribution
``ggx_rgb``     ``ggx`` with a coloured specular F0 in [0, 1] (metals): 7 parameters
``ggx_normal``  ``ggx`` with a per-pixel normal perturbation (:class:`jaxrefl.brdf.NormalTilt`:
                slopes ``tilt_x``, ``tilt_y`` in [-1, 1] of the shading normal; the maps
                add ``normal.X/Y/Z``): 7 parameters. Fitted in two stages: ``ggx`` from
                the automatic start, then all 7 from that optimum with the tilt at 0
                (:data:`TWO_STAGE`).
``pooled``      ``ggx_rgb`` with one GGX ``alpha`` shared by every pixel, chosen with Lambert
                as the alternative by leave-one-photo-out over the training photos, and an
                empirical-Bayes prior on F0 (:mod:`jaxrefl.svbrdf._pooled`): 6 parameters
                per pixel. What the photos identify for a real capture.
``lambert``     Lambertian ``albedo`` (RGB) only: the diffuse-only baseline
=============  ============================================================================
"""

from __future__ import annotations

from jaxrefl import brdf
from jaxrefl._errors import JaxreflError
from jaxrefl._names import CAPTURE_MODELS, canonical
from jaxrefl.fit import ParamSpace

__all__ = ["ALPHA_RANGE", "CAPTURE_MODELS", "DIELECTRIC_F0", "TWO_STAGE", "capture_model"]

# A grey specular is a dielectric's: F0 = ((eta - 1)/(eta + 1))^2 <= 0.25 for eta <= 3
# (glass 0.04, diamond 0.17). Without the cap, pixels whose highlight was only seen
# saturated (censored: any brighter prediction fits) run off to F0 -> 1 with a needle lobe.
DIELECTRIC_F0 = (0.0, 0.25)
# alpha above 1 makes the specular lobe broader than a cosine: indistinguishable from more
# diffuse albedo, so the pair is not identified. The lower end is the capture's resolvable
# width (``jaxrefl.svbrdf.resolvable_alpha``), at least 1e-3 (the microfacet models' floor).
ALPHA_RANGE = (1e-3, 1.0)

# Models fitted from another model's optimum (name -> the first stage's model). The
# automatic start grids one nonlinear scalar (alpha); with two slopes as well it would fall
# back to a weak multi-start, while the flat fit is a close start (tilts are small).
TWO_STAGE: dict[str, str] = {"ggx_normal": "ggx"}


def capture_model(
    name: str, channels: int = 3, alpha_min: float | None = None, alpha: float | None = None
) -> tuple[brdf.BRDF, ParamSpace]:
    """(model, parameter space) of a capture model named in :data:`CAPTURE_MODELS`;
    ``alpha_min`` raises the lower bound of alpha (default 1e-3); ``alpha``: the shared
    width of ``pooled`` (required there; None with ``pooled`` gives its Lambert choice)."""
    name = canonical(name)
    if name == "pooled":
        if alpha is None:
            return capture_model("lambert", channels)
        m, _ = capture_model("ggx_rgb", channels)
        return m, ParamSpace(m, channels=channels, fixed={"alpha": float(alpha)})
    lo = ALPHA_RANGE[0] if alpha_min is None else max(ALPHA_RANGE[0], float(alpha_min))
    alpha_range = (lo, ALPHA_RANGE[1])
    if name == "lambert":
        m = brdf.get("lambert")
        return m, ParamSpace(m, channels=channels)
    if name == "ggx_normal":
        base, _ = capture_model("ggx", channels, alpha_min)
        m = brdf.NormalTilt(base)
        bounds = {"specular": DIELECTRIC_F0, "alpha": alpha_range}
        return m, ParamSpace(m, channels=channels, grey=("specular",), bounds=bounds)
    if name in ("ggx", "beckmann", "ggx_rgb"):
        m = brdf.get(
            "cook_torrance",
            distribution="beckmann" if name == "beckmann" else "ggx",
            shadowing="smith_height_correlated",
            fresnel="schlick",
            diffuse="lambert",
        )
        if name == "ggx_rgb":
            return m, ParamSpace(m, channels=channels, bounds={"alpha": alpha_range})
        bounds = {"specular": DIELECTRIC_F0, "alpha": alpha_range}
        return m, ParamSpace(m, channels=channels, grey=("specular",), bounds=bounds)
    raise JaxreflError(f"unknown capture model {name!r}; choose from {', '.join(CAPTURE_MODELS)}")
