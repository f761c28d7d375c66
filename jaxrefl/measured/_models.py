"""The analytic models fitted to measured BRDFs, by name.

Every model is a Lambertian base (``albedo``, colour in [0, 1], f_r = albedo/pi) plus one
specular part; each returns f_r in 1/sr without the cosine factor (see the model modules for
the equations and parameter ranges):

=========================  ==============================================================
name                       model
=========================  ==============================================================
``lambert``                albedo/pi (``Lambert``)
``blinn_phong``            + specular (n + 8)/(8 pi) cos^n theta_h (``BlinnPhong``,
                           normalised so that it is reciprocal and ``specular`` stays in
                           [0, 1] for sharp highlights)
``ward``                   + Ward's isotropic Gaussian lobe (``Ward``, Ward 1992 form)
``beckmann``               + F D G / (4 cos_i cos_o) with Beckmann D, height-correlated
                           Smith G, Schlick F (``specular`` = F0) (``CookTorrance``)
``ggx``                    the same with GGX D
``lafortune_1`` .. ``_3``  + 1, 2 or 3 generalised cosine lobes (``Lafortune``)
=========================  ==============================================================

``DEFAULT_MODELS`` lists them in that order (the set of the foundation issue). The names are
those of :data:`jaxrefl._names.MEASURED_MODELS`, shared with the command line;
:func:`build_model` also takes their aliases (``cook_torrance_ggx`` for ``ggx``).

Each Cook-Torrance model also comes with the exact unpolarised dielectric Fresnel term
(Hecht, *Optics*, sec. 4.6) and a fitted relative index ``eta`` per channel in [1, 4] in
place of Schlick's F0: ``beckmann_dielectric`` and
``ggx_dielectric`` (not in the default set; :data:`FRESNEL_CHOICES` names the
two terms and :func:`fresnel_variant` maps a model name to the variant with either).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

from jaxrefl._errors import JaxreflError
from jaxrefl._names import MEASURED_MODELS, canonical
from jaxrefl.brdf import (
    BRDF,
    BlinnPhong,
    ConductorFresnel,
    CookTorrance,
    DielectricFresnel,
    Lafortune,
    Lambert,
    NoFresnel,
    SchlickFresnel,
    Ward,
)

__all__ = [
    "DEFAULT_MODELS",
    "FRESNEL_CHOICES",
    "MODEL_DESCRIPTIONS",
    "MODEL_NAMES",
    "build_model",
    "fresnel_name",
    "fresnel_variant",
    "resolve_models",
]

_BUILDERS: dict[str, Callable[[], BRDF]] = {
    "lambert": Lambert,
    "blinn_phong": lambda: BlinnPhong(normalized=True),
    "ward": Ward,
    "beckmann": lambda: CookTorrance("beckmann", diffuse="lambert"),
    "ggx": lambda: CookTorrance("ggx", diffuse="lambert"),
    "lafortune_1": lambda: Lafortune(num_lobes=1),
    "lafortune_2": lambda: Lafortune(num_lobes=2),
    "lafortune_3": lambda: Lafortune(num_lobes=3),
}

#: Every model of the default set, in report order.
DEFAULT_MODELS: tuple[str, ...] = tuple(_BUILDERS)

#: The Fresnel terms a Cook-Torrance model of this set can have.
FRESNEL_CHOICES: tuple[str, ...] = ("schlick", "dielectric")
_DIELECTRIC = "_dielectric"


def _dielectric(distribution: str) -> Callable[[], BRDF]:
    return lambda: CookTorrance(distribution, diffuse="lambert", fresnel="dielectric")


for _d in ("beckmann", "ggx"):
    _BUILDERS[f"{_d}{_DIELECTRIC}"] = _dielectric(_d)

#: Every model name :func:`build_model` knows (the default set first).
MODEL_NAMES: tuple[str, ...] = tuple(_BUILDERS)
#: One line per model name.
MODEL_DESCRIPTIONS: dict[str, str] = dict(MEASURED_MODELS)


def build_model(name: str) -> BRDF:
    """The model called ``name`` (one of :data:`MODEL_NAMES`)."""
    try:
        return _BUILDERS[canonical(name)]()
    except KeyError:
        raise JaxreflError(
            f"unknown model {name!r}; choose from {', '.join(MODEL_NAMES)}"
        ) from None


_FRESNEL_NAMES = {
    SchlickFresnel: "schlick",
    DielectricFresnel: "dielectric",
    ConductorFresnel: "conductor",
    NoFresnel: "none",
}


def fresnel_name(model: BRDF) -> str | None:
    """``"schlick"``, ``"dielectric"``, ``"conductor"`` or ``"none"``: the Fresnel part
    of a microfacet model; None for a model without one."""
    part = getattr(model, "fresnel", None)
    return None if part is None else _FRESNEL_NAMES.get(type(part), type(part).__name__)


def fresnel_variant(name: str, fresnel: str) -> str:
    """The name of model ``name`` with Fresnel term ``fresnel`` (one of
    :data:`FRESNEL_CHOICES`); a model without a Fresnel variant keeps its name."""
    if fresnel not in FRESNEL_CHOICES:
        raise JaxreflError(f"fresnel must be one of {', '.join(FRESNEL_CHOICES)}, not {fresnel!r}")
    base = canonical(name).removesuffix(_DIELECTRIC)
    if base + _DIELECTRIC not in _BUILDERS:
        return canonical(name)
    return base + (_DIELECTRIC if fresnel == "dielectric" else "")


def resolve_models(models: Iterable[str] | Mapping[str, BRDF] | None) -> dict[str, BRDF]:
    """``None`` -> every default model; names -> built models; a dict is used as given."""
    if models is None:
        models = DEFAULT_MODELS
    if isinstance(models, Mapping):
        return dict(models)
    if isinstance(models, str):
        models = [models]
    out = {canonical(n): build_model(n) for n in models}
    if not out:
        raise JaxreflError("no models to fit")
    return out
