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
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

from jaxrefl._names import MEASURED_MODELS, canonical
from jaxrefl.brdf import BRDF, BlinnPhong, CookTorrance, Lafortune, Lambert, Ward

__all__ = ["DEFAULT_MODELS", "MODEL_DESCRIPTIONS", "build_model", "resolve_models"]

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
#: One line per model name.
MODEL_DESCRIPTIONS: dict[str, str] = dict(MEASURED_MODELS)


def build_model(name: str) -> BRDF:
    """The model called ``name`` (one of :data:`DEFAULT_MODELS`)."""
    try:
        return _BUILDERS[canonical(name)]()
    except KeyError:
        raise ValueError(
            f"unknown model {name!r}; choose from {', '.join(DEFAULT_MODELS)}"
        ) from None


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
        raise ValueError("no models to fit")
    return out
