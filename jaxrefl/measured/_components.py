"""A reflectance model assembled from components that are switched on or off.

    f_r = [albedo / pi]                                         diffuse base (Lambert)
        + [F(wo.h) D(h) G / (4 cos_i cos_o)]                    specular lobe (Cook-Torrance)
        + [F_2 D_2 G_2 / (4 cos_i cos_o)]                       second lobe (own F0, alpha)
        + [retro (n + 2)/(2 pi) max(wi.wo, 0)^n]                retro-reflection lobe   [1/sr]

returned **without** the cosine factor, directions away from the surface in the local frame
(z = normal). The switches of :class:`Components`:

=================  ===========================================================  ===========
switch             what it adds                                                   parameters
=================  ===========================================================  ===========
``diffuse``        Lambert base, albedo in [0, 1]                                 ``albedo``
``lobe``           ``"ggx"`` or ``"beckmann"`` microfacet lobe, height-correlated ``specular``
                   Smith G (:class:`~jaxrefl.brdf.CookTorrance`), alpha in        ``alpha``
                   [1e-4, 1]
``fresnel``        Schlick F = F0 + (1 - F0)(1 - cos)^5 with F0 = ``specular``;    (none new)
                   off: F = ``specular``, an angle-independent scale
``anisotropic``    alpha_u (tangent x) and alpha_v (y) instead of alpha          ``alpha_u``,
                                                                                  ``alpha_v``
``second_lobe``    a second isotropic lobe of the same kind and Fresnel           ``specular_2``,
                                                                                  ``alpha_2``
``retro``          a retro-reflection lobe around wo = wi: the Lafortune et al.   ``retro``
                   (1997) lobe with C_x = C_y = C_z = 1 in this sign convention,
                   normalised so that its albedo at normal incidence is
                   ``retro`` in [0, 1]; exponent n fixed (``retro_exponent``,
                   default 8), so the lobe is linear in its one parameter
=================  ===========================================================  ===========

``fresnel``, ``anisotropic`` and ``second_lobe`` refine the lobe and need it. The compiled
forward model holds only what is switched on: :meth:`Components.build` returns a
:class:`~jaxrefl.brdf.Sum` of the chosen parts (a single part on its own), so a diffuse-only
scene evaluates albedo / pi and nothing else (``benchmarks/components_cost.py`` measures
the difference against a model that carries a zero-strength lobe).

Fitting: :func:`param_space` gives the second lobe's ``alpha_2`` the same log-scale
bijection as ``alpha`` (the default choice goes by name); :func:`start_from` turns a fit of
one assembly into the natural starting values of another (shared parameters kept, alpha <->
alpha_u/alpha_v by the geometric mean, new components small); :func:`fit_components` fits
an assembly, by default from the automatic start of its core (diffuse + one isotropic
lobe), where the closed-form colours on a roughness grid of ``jaxrefl.fit`` apply.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF, CookTorrance, Lambert, Param, Sum
from jaxrefl.fit import Bijection, Exp, FitConfig, FitResult, ParamSpace, PixelData, fit_pixels

__all__ = [
    "COMPONENT_NAMES",
    "Components",
    "Renamed",
    "RetroLobe",
    "core",
    "fit_components",
    "param_space",
    "start_from",
]

#: Every switch of :class:`Components`, in the order of :attr:`Components.active`.
COMPONENT_NAMES = ("diffuse", "lobe", "fresnel", "anisotropic", "second_lobe", "retro")
# Switches that refine the lobe and are meaningless without it.
_NEEDS_LOBE = ("fresnel", "anisotropic", "second_lobe")
_LOBES = ("ggx", "beckmann")
# Widths act on a log scale (as in jaxrefl.fit's default choice); matched by stem.
_LOG_STEMS = ("alpha", "alpha_u", "alpha_v")

RETRO = Param(
    name="retro",
    kind="color",
    default=0.05,
    lower=0.0,
    upper=1.0,
    units="1 (albedo of the retro lobe at normal incidence)",
    doc="strength of the retro-reflection lobe per channel",
)


class RetroLobe(BRDF):
    """f_r = retro (n + 2)/(2 pi) max(wi . wo, 0)^n  [1/sr], no cosine factor.

    A cosine lobe about the back-scattering direction wo = wi (Lafortune et al. 1997, lobe
    with C_x = C_y = C_z = 1 when both directions point away from the surface). At normal
    incidence int f_r cos_o dwo = retro exactly; elsewhere the horizon cuts the lobe, so the
    albedo is <= retro. Reciprocal (wi . wo is symmetric). ``exponent`` n >= 1 is fixed at
    construction, so f_r is linear in ``retro`` (colour in [0, 1]).
    """

    exponent: float = eqx.field(static=True, default=8.0)

    def __check_init__(self):
        if not self.exponent >= 1.0:
            raise JaxreflError(f"RetroLobe exponent must be >= 1, got {self.exponent}")

    @property
    def params(self) -> tuple[Param, ...]:
        return (RETRO,)

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b C"]:
        d = jnp.sum(wi * wo, axis=-1)
        # Back-facing pairs (wi . wo <= 0) lie outside the lobe; 0^n with n >= 1 has a
        # finite (zero) gradient, so clamping the base is gradient-safe.
        c = jnp.where(d > 0.0, d, 0.0)
        n = self.exponent
        lobe = (n + 2.0) / (2.0 * jnp.pi) * c**n
        return p["retro"] * lobe[..., None]


class Renamed(BRDF):
    """``inner`` with every parameter name followed by ``suffix`` (a second copy of a
    component inside one :class:`~jaxrefl.brdf.Sum`, whose names must not clash)."""

    inner: BRDF
    suffix: str = eqx.field(static=True)

    @property
    def params(self) -> tuple[Param, ...]:
        return tuple(dataclasses.replace(q, name=q.name + self.suffix) for q in self.inner.params)

    @property
    def reciprocal(self) -> bool:
        return self.inner.reciprocal

    @property
    def energy_conserving(self) -> bool:
        return self.inner.energy_conserving

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b C"]:
        return self.inner._eval(
            {q.name: p[q.name + self.suffix] for q in self.inner.params}, wi, wo
        )


@dataclasses.dataclass(frozen=True)
class Components:
    """Which components a model is assembled from (module docstring)."""

    diffuse: bool = True
    lobe: str | None = "ggx"
    fresnel: bool = True
    anisotropic: bool = False
    second_lobe: bool = False
    retro: bool = False
    retro_exponent: float = 8.0

    def __post_init__(self):
        if self.lobe is not None and self.lobe not in _LOBES:
            raise JaxreflError(f"lobe must be None or one of {_LOBES}, not {self.lobe!r}")
        if self.lobe is None:
            on = [s for s in _NEEDS_LOBE if getattr(self, s)]
            if on:
                raise JaxreflError(f"{', '.join(on)} refine the specular lobe; switch on lobe=")
        if not self.active:
            raise JaxreflError("a model needs at least one component (diffuse, lobe or retro)")

    @property
    def active(self) -> tuple[str, ...]:
        """Names of the switches that are on, in :data:`COMPONENT_NAMES` order."""
        return tuple(n for n in COMPONENT_NAMES if (getattr(self, n) if n != "lobe" else self.lobe))

    @property
    def label(self) -> str:
        """e.g. ``"diffuse+ggx+fresnel+retro"``."""
        return "+".join(self.lobe if n == "lobe" else n for n in self.active)  # type: ignore[misc]

    def without(self, name: str) -> Components:
        """The same assembly with component ``name`` off (``"lobe"`` takes its refinements
        with it)."""
        if name not in self.active:
            raise JaxreflError(f"{name!r} is not switched on in {self.label}")
        if name == "lobe":
            return dataclasses.replace(
                self, lobe=None, fresnel=False, anisotropic=False, second_lobe=False
            )
        return dataclasses.replace(self, **{name: False})  # type: ignore[arg-type]

    def removals(self) -> dict[str, Components]:
        """Every assembly with one active component removed (empty ones left out)."""
        out = {}
        for n in self.active:
            try:
                out[n] = self.without(n)
            except ValueError:  # removing the last component
                continue
        return out

    def parts(self) -> list[BRDF]:
        """The component BRDFs that are switched on."""
        parts: list[BRDF] = []
        fr = "schlick" if self.fresnel else "none"
        if self.diffuse:
            parts.append(Lambert())
        if self.lobe is not None:
            parts.append(CookTorrance(self.lobe, self.anisotropic, fresnel=fr))
            if self.second_lobe:
                parts.append(Renamed(CookTorrance(self.lobe, False, fresnel=fr), "_2"))
        if self.retro:
            parts.append(RetroLobe(float(self.retro_exponent)))
        return parts

    def build(self) -> BRDF:
        """The assembled model: the one part, or a :class:`~jaxrefl.brdf.Sum` of them."""
        parts = self.parts()
        return parts[0] if len(parts) == 1 else Sum(*parts)


def _stem(name: str) -> str:
    return name[: -len("_2")] if name.endswith("_2") else name


def param_space(
    model: BRDF,
    channels: int = 3,
    *,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    fixed: Mapping[str, Any] | None = None,
    transforms: Mapping[str, Bijection] | None = None,
    grey: tuple[str, ...] = (),
) -> ParamSpace:
    """:class:`~jaxrefl.fit.ParamSpace` of an assembled model: renamed widths (``alpha_2``)
    get ``Exp(lower)`` as ``alpha`` does; ``bounds``, ``fixed``, ``transforms`` (taking
    precedence over those) and ``grey`` are those of ParamSpace."""
    trans = dict(transforms or {})
    for q in model.params:
        if q.name != _stem(q.name) and _stem(q.name) in _LOG_STEMS and q.name not in (fixed or {}):
            trans.setdefault(q.name, Exp(q.lower))
    return ParamSpace(
        model, channels=channels, bounds=bounds, fixed=fixed, transforms=trans, grey=grey
    )


def core(spec: Components) -> Components:
    """Diffuse (if on) plus one isotropic lobe (if on) with the spec's Fresnel; or the spec
    itself when it has neither."""
    if spec.lobe is None and not spec.diffuse:
        return spec
    return Components(
        diffuse=spec.diffuse,
        lobe=spec.lobe,
        fresnel=spec.fresnel if spec.lobe else False,
        retro_exponent=spec.retro_exponent,
    )


def start_from(
    params: Mapping[str, Any], spec: Components, n: int, channels: int
) -> dict[str, np.ndarray]:
    """Natural starting values (leading axis ``n``) of assembly ``spec`` from the fitted
    ``params`` of another assembly: shared names are copied; alpha from alpha_u/alpha_v by
    the geometric mean and back; a new second lobe starts at a quarter of the first lobe's
    strength and four times its width (capped at 0.8); other new parameters at their
    defaults (retro 0.02)."""
    p = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
    if "alpha" not in p and "alpha_u" in p:
        p["alpha"] = np.sqrt(p["alpha_u"] * p["alpha_v"])
    if "alpha" in p:
        p.setdefault("alpha_u", p["alpha"])
        p.setdefault("alpha_v", p["alpha"])
    if "specular" in p:
        p.setdefault("specular_2", 0.25 * p["specular"])
    if "alpha" in p:
        p.setdefault("alpha_2", np.minimum(4.0 * p["alpha"], 0.8))
    p.setdefault("retro", np.full((n, channels), 0.02))
    out = {}
    for q in spec.build().params:
        if q.name in p:
            v = p[q.name]
        else:
            v = np.asarray(q.default, dtype=np.float64)
        shape = (n, channels) if q.kind == "color" else (n,)
        if q.kind == "color" and v.ndim == 1 and v.shape[0] == n and n != channels:
            v = v[:, None]
        out[q.name] = np.broadcast_to(v, shape).copy()
    return out


def fit_components(
    spec: Components,
    data: PixelData,
    *,
    init: Mapping[str, Any] | None = None,
    config: FitConfig = FitConfig(),
    devices: int | None = None,
) -> FitResult:
    """Fit assembly ``spec`` to every pixel of ``data`` with :func:`jaxrefl.fit.fit_pixels`
    in :func:`param_space`.

    init:    natural starting values (e.g. :func:`start_from` a richer fit); default: the
             automatic start when ``spec`` is its own :func:`core`, else a fit of the core
             followed by :func:`start_from` it.
    config:  solver, noise, loss and dtype of the fits (:class:`jaxrefl.fit.FitConfig`;
             dtype None: that of ``data.obs``)
    devices: as for ``fit_pixels`` (default all)
    """
    model = spec.build()
    c = data.obs.shape[-1]
    n = data.obs.shape[0]
    space = param_space(model, c)
    if init is None:
        base = core(spec)
        if base == spec:
            return fit_pixels(model, data, config=config, space=space, devices=devices)
        r0 = fit_pixels(
            base.build(), data, config=config, space=param_space(base.build(), c), devices=devices
        )
        init = start_from(r0.params, spec, n, c)
    dtype = data.obs.dtype if config.dtype is None else np.dtype(config.dtype)
    init_j = {k: jnp.asarray(np.nan_to_num(np.asarray(v), nan=0.1), dtype) for k, v in init.items()}
    return fit_pixels(model, data, config=config, space=space, init=init_j, devices=devices)
