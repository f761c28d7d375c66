"""Model names shared by the library and the command line, importable without JAX.

One naming scheme for every place a model is chosen by name (``jaxrefl models``,
``jaxrefl fit --model``, ``jaxrefl fit-brdf --models``, ``jaxrefl sample --model`` and
``--brdf-model``):

- **families** (:func:`jaxrefl.brdf.get`): a BRDF class whose parts are options
  (``cook_torrance`` with a distribution, a shadowing term, a Fresnel term, a base);
- **configured models**: a family with its parts fixed, fitted by ``fit-brdf``
  (:data:`MEASURED_MODELS`), and the per-pixel capture models of ``fit`` and ``sample``
  (:data:`CAPTURE_MODELS`). A name in both tables is the same physical model
  (``ggx``: Lambert + Cook–Torrance with GGX D, height-correlated Smith G, Schlick F);
  the capture tables add per-pixel bounds (:mod:`jaxrefl.svbrdf`).

Older spellings are accepted as aliases (:data:`ALIASES`) and resolved by
:func:`canonical`; outputs and reports always carry the canonical name.
"""

from __future__ import annotations

__all__ = [
    "ALIASES",
    "CAPTURE_MODELS",
    "FAMILIES",
    "ILLUMINANTS",
    "LIGHT_CHOICES",
    "LIGHT_DEFAULT",
    "MEASURED_MODELS",
    "NOISE_LEVELS",
    "SPECTRAL_CHOICES",
    "canonical",
    "describe",
]

#: What a capture fit does with its flash (``jaxrefl fit --light``, ``svbrdf.FitJob.light``):
#: as stated, its offset from the lens estimated, the offset and a gain per photo, or auto.
LIGHT_CHOICES: tuple[str, ...] = ("fixed", "offset", "offset+gains", "auto")
#: The flash of ``jaxrefl fit`` and ``jaxrefl sample`` when ``--light`` is not given, and of
#: ``svbrdf.FitJob``: ``auto`` moves it from where the capture states it only where held-out
#: photos support the move (docs/light.md).
LIGHT_DEFAULT = "auto"

#: A capture fit's noise (``--noise-level``, ``svbrdf.FitJob.noise_level``), the default
#: first: ``auto`` the capture's noise-level function where its residuals support it,
#: ``flat`` one noise level per pixel.
NOISE_LEVELS: tuple[str, ...] = ("auto", "flat")

#: How a measured fit takes spectral data (``jaxrefl fit-brdf --spectral``,
#: ``measured.MeasuredOptions.spectral``): as RGB, or one problem a band; the default first.
SPECTRAL_CHOICES: tuple[str, ...] = ("rgb", "bands")
#: The illuminants of their RGB conversion (``--illuminant``, ``MeasuredOptions.illuminant``).
ILLUMINANTS: tuple[str, ...] = ("D65", "E")

#: BRDF families of :func:`jaxrefl.brdf.get` -> one line.
FAMILIES: dict[str, str] = {
    "lambert": "Lambertian diffuse, f_r = albedo/pi",
    "oren_nayar": "Oren-Nayar rough diffuse",
    "phong": "Lambert + modified Phong lobe",
    "blinn_phong": "Lambert + Blinn-Phong lobe",
    "lafortune": "Lambert + generalised cosine lobes",
    "ward": "Lambert + Ward (1992) anisotropic Gaussian lobe",
    "cook_torrance": "microfacet specular (distribution, shadowing, Fresnel as options) + base",
    "dichromatic": "diffuse + specular with a shared illuminant colour",
}

#: Per-pixel models of a flash capture (``jaxrefl fit --model``, :mod:`jaxrefl.svbrdf`).
CAPTURE_MODELS: dict[str, str] = {
    "ggx": "Cook-Torrance GGX + Lambert, grey specular F0 (albedo RGB, specular, alpha)",
    "beckmann": "Cook-Torrance Beckmann + Lambert, grey specular F0",
    "ggx_rgb": "Cook-Torrance GGX + Lambert, coloured specular F0",
    "ggx_normal": "ggx with a per-pixel normal perturbation (tilt_x, tilt_y slopes)",
    "pooled": "ggx_rgb with one alpha for the capture, chosen by held-out photos, F0 pooled",
    "lambert": "Lambertian albedo only (diffuse baseline)",
}

#: Models fitted to a measured BRDF (``jaxrefl fit-brdf --models``, :mod:`jaxrefl.measured`),
#: in report order; every colour parameter is per channel.
MEASURED_MODELS: dict[str, str] = {
    "lambert": "Lambert",
    "blinn_phong": "Lambert + normalised Blinn-Phong lobe",
    "ward": "Lambert + Ward (1992) isotropic lobe",
    "beckmann": "Lambert + Cook-Torrance, Beckmann D, height-correlated Smith G, Schlick F",
    "ggx": "Lambert + Cook-Torrance, GGX D, height-correlated Smith G, Schlick F",
    "lafortune_1": "Lambert + 1 Lafortune lobe",
    "lafortune_2": "Lambert + 2 Lafortune lobes",
    "lafortune_3": "Lambert + 3 Lafortune lobes",
    "beckmann_dielectric": "beckmann with the exact dielectric Fresnel term (fitted eta)",
    "ggx_dielectric": "ggx with the exact dielectric Fresnel term (fitted eta)",
}

#: Other spellings -> the canonical name.
ALIASES: dict[str, str] = {
    "cook_torrance_ggx": "ggx",
    "cook_torrance_beckmann": "beckmann",
    "ct_ggx": "ggx",
    "ct_beckmann": "beckmann",
    "cook_torrance_ggx_dielectric": "ggx_dielectric",
    "cook_torrance_beckmann_dielectric": "beckmann_dielectric",
    "ggx_normals": "ggx_normal",
}


def canonical(name: str) -> str:
    """The canonical spelling of a model name: lower case, ``-`` as ``_``, aliases resolved.

    Unknown names are returned normalised; the caller says what would be valid."""
    key = name.strip().lower().replace("-", "_")
    return ALIASES.get(key, key)


# Where uncertainty_maps takes a capture's priors (jaxrefl.svbrdf.uncertainty_maps, sample
# --priors): estimated from the reliably fitted pixels, or the model's defaults.
PRIOR_SOURCES = ("population", "default")

# What ranks a capture plan's candidates (jaxrefl.svbrdf.PlanOptions.criterion, plan
# --criterion), the default first: jaxrefl/svbrdf/_plan.py says what each computes.
PLAN_CRITERIA = ("variance", "log_variance", "information")


def describe(name: str) -> list[str]:
    """What ``name`` (any spelling) means in each table it belongs to, one line each;
    empty when it names nothing."""
    key = canonical(name)
    lines = []
    if key in FAMILIES:
        lines.append(f"BRDF family (jaxrefl.brdf.get): {FAMILIES[key]}")
    if key in CAPTURE_MODELS:
        lines.append(f"capture model (fit --model, sample --model): {CAPTURE_MODELS[key]}")
    if key in MEASURED_MODELS:
        lines.append(
            f"measured-BRDF model (fit-brdf --models, sample --brdf-model): {MEASURED_MODELS[key]}"
        )
    return lines


def all_names() -> list[str]:
    """Every canonical name, sorted."""
    return sorted(set(FAMILIES) | set(CAPTURE_MODELS) | set(MEASURED_MODELS))
