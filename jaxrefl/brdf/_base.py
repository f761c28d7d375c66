"""The evaluation contract every BRDF model follows.

``m.eval(params, wi, wo)`` returns f_r(wi, wo) in 1/sr, **without** the cosine factor.

* ``params`` is a dict (pytree) of arrays whose keys are exactly ``m.param_names``.
* ``wi`` and ``wo`` are unit vectors, shape ``(*batch, 3)``, in the local shading frame
  (z = surface normal), both pointing away from the surface.
* Parameter kinds (see :class:`Param`):

  - ``"scalar"``: shape ``(*batch,)`` (or ``()``), e.g. ``alpha``, ``exponent``, ``sigma``.
  - ``"color"``: shape ``(*batch, C)`` with a trailing channel axis (``C = 1`` for grey, 3 for
    RGB, or any number of spectral bands); a Python float or 0-d array is taken as ``C = 1``.
  - ``"lobes"``: shape ``(*batch, L, 4)``, rows ``(Cx, Cy, Cz, n)`` (Lafortune).

* Everything broadcasts over leading dimensions; the result has shape ``(*batch, C)`` where
  C broadcasts over the colour parameters.
* Directions at or below the horizon (cos <= 0 for either) give exactly 0 and zero gradients:
  :meth:`BRDF.eval` swaps such directions for the normal *before* evaluating (gradient-safe
  guard), then zeroes the result.
* The dtype of the result is the dtype of ``wi``; parameters are cast to it.

Validation: :meth:`BRDF.check_params` refuses a non-finite parameter or one outside its
documented range ``[lower, upper]`` (Ward with alpha = 0, a dielectric with eta = 0), and
:func:`check_directions` refuses finite directions that are not unit vectors; both raise
a ValueError naming the parameter or argument. :meth:`BRDF.eval` applies both to concrete
(not traced) inputs while validation is on: ``set_validation(True)`` or the environment
variable ``JAXREFL_VALIDATE=1``. It is off by default (inside fits the inputs are traced
and already checked at the boundary: ``jaxrefl.fit.pixel_data``, ``ParamSpace``).
"""

from __future__ import annotations

import abc
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxrefl._errors import JaxreflError

from ._frame import cos_theta, upper_hemisphere

__all__ = ["BRDF", "Param", "Params", "check_directions", "set_validation"]

# Largest accepted | |w| - 1 | of a direction under validation.
_UNIT_TOL = 1e-3
_VALIDATE = [os.environ.get("JAXREFL_VALIDATE", "") == "1"]


def set_validation(on: bool) -> bool:
    """Turn :meth:`BRDF.eval`'s input checks on or off; returns the previous setting."""
    before = _VALIDATE[0]
    _VALIDATE[0] = bool(on)
    return before


def _concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


def check_directions(wi: ArrayLike, wo: ArrayLike) -> None:
    """Refuse finite ``wi``/``wo`` that are not unit vectors (within 1e-3), naming the
    argument and its worst length. Non-finite directions are left to the caller."""
    for name, w in (("wi", wi), ("wo", wo)):
        w = np.asarray(w, np.float64)
        norm = np.sqrt(np.sum(w * w, axis=-1))
        off = np.where(np.isfinite(norm), np.abs(norm - 1.0), 0.0)
        if off.size and np.max(off) > _UNIT_TOL:
            i = np.unravel_index(int(np.argmax(off)), off.shape)
            raise JaxreflError(
                f"{name} must be unit vectors (|{name}| = 1 within {_UNIT_TOL:g}); the worst, "
                f"at index {tuple(int(j) for j in i)}, has length {float(norm[i]):.6g}"
            )


Params = Mapping[str, ArrayLike]
ParamKind = Literal["scalar", "color", "lobes"]


@dataclass(frozen=True)
class Param:
    """Description of one model parameter, in natural units.

    ``lower``/``upper`` are the physically meaningful range (inclusive where finite); fitting
    code maps them to an unconstrained space. ``default`` is a typical value used by demos,
    tests and initialisation.
    """

    name: str
    kind: ParamKind
    default: float | tuple[float, ...]
    lower: float
    upper: float
    units: str
    doc: str


class BRDF(eqx.Module):
    """Base class. Subclasses declare :attr:`params` and implement :meth:`_eval`.

    Properties :attr:`reciprocal` and :attr:`energy_conserving` say which physical laws the
    configured model obeys; subclasses override them (the tests check both claims).
    """

    @property
    def reciprocal(self) -> bool:
        """Whether f(wi, wo) == f(wo, wi) for every parameter value."""
        return True

    @property
    def energy_conserving(self) -> bool:
        """Whether the directional albedo is <= 1 for every parameter value in range
        (colour/scale parameters <= 1); tests integrate it numerically."""
        return False

    @property
    @abc.abstractmethod
    def params(self) -> tuple[Param, ...]:
        """The model's parameters, in a fixed order."""

    @abc.abstractmethod
    def _eval(
        self,
        p: dict[str, Array],
        wi: Float[Array, "*b 3"],
        wo: Float[Array, "*b 3"],
    ) -> Float[Array, "*b C"]:
        """f_r for directions strictly in the upper hemisphere.

        ``p`` holds arrays cast to the direction dtype; colour parameters already carry a
        trailing channel axis. Return shape ``(*batch, C)``.
        """

    # ------------------------------------------------------------------ public API
    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(q.name for q in self.params)

    def param_spec(self, name: str) -> Param:
        for q in self.params:
            if q.name == name:
                return q
        raise KeyError(
            f"{type(self).__name__} has no parameter {name!r}; it has {self.param_names}"
        )

    def check_params(self, params: Params) -> None:
        """Refuse a parameter that is missing, non-finite or outside ``[lower, upper]``
        (:class:`Param`), naming it and its range. Lafortune lobes are checked for
        finiteness only (their rows mix coefficients and exponents)."""
        for q in self.params:
            if q.name not in params:
                raise KeyError(f"{type(self).__name__}: missing parameter {q.name!r}")
            v = params[q.name]
            if not _concrete(v):
                continue
            v = np.asarray(v, np.float64)
            if not np.all(np.isfinite(v)):
                raise JaxreflError(
                    f"{type(self).__name__} parameter {q.name!r} = {v.tolist()} is not finite; "
                    f"give a value in [{q.lower:g}, {q.upper:g}]"
                )
            if q.kind != "lobes" and (np.any(v < q.lower) or np.any(v > q.upper)):
                raise JaxreflError(
                    f"{type(self).__name__} parameter {q.name!r} = {v.tolist()} is outside its "
                    f"range [{q.lower:g}, {q.upper:g}] ({q.doc})"
                )

    def default_params(self, dtype=jnp.float32) -> dict[str, Array]:
        """A dict of typical parameter values (colour parameters as RGB, shape (3,))."""
        out = {}
        for q in self.params:
            v = jnp.asarray(q.default, dtype=dtype)
            if q.kind == "color" and v.ndim == 0:
                v = jnp.full((3,), v, dtype=dtype)
            out[q.name] = v
        return out

    def eval(
        self,
        params: Params,
        wi: Float[ArrayLike, "*b 3"],
        wo: Float[ArrayLike, "*b 3"],
    ) -> Float[Array, "*b C"]:
        """f_r(wi, wo) in 1/sr (no cosine factor); 0 below the horizon."""
        wi = jnp.asarray(wi)
        wo = jnp.asarray(wo)
        if not jnp.issubdtype(wi.dtype, jnp.floating):
            wi = wi.astype(jnp.float32)
        wo = wo.astype(wi.dtype)
        if wi.shape[-1:] != (3,) or wo.shape[-1:] != (3,):
            raise JaxreflError(
                f"wi and wo must have a trailing axis of length 3, got {wi.shape} and {wo.shape}"
            )
        if _VALIDATE[0] and _concrete(wi, wo, *jax.tree.leaves(dict(params))):
            self.check_params(params)
            check_directions(wi, wo)
        p = self._prepare(params, wi.dtype)
        p, wi, wo = self._align_ranks(p, wi, wo)
        ok = upper_hemisphere(wi, wo)
        # Gradient-safe guard: evaluate below-horizon samples at the normal, then zero them.
        up = jnp.asarray([0.0, 0.0, 1.0], dtype=wi.dtype)
        wi_s = jnp.where(ok[..., None], wi, up)
        wo_s = jnp.where(ok[..., None], wo, up)
        f = self._eval(p, wi_s, wo_s)
        return jnp.where(ok[..., None], f, jnp.zeros((), dtype=f.dtype))

    def eval_cos(
        self,
        params: Params,
        wi: Float[ArrayLike, "*b 3"],
        wo: Float[ArrayLike, "*b 3"],
    ) -> Float[Array, "*b C"]:
        """f_r(wi, wo) * max(cos(theta_i), 0): the integrand of the reflectance equation."""
        f = self.eval(params, wi, wo)
        ci = jnp.maximum(cos_theta(jnp.asarray(wi, dtype=f.dtype)), 0.0)
        return f * ci[..., None]

    __call__ = eval

    # ------------------------------------------------------------------ helpers
    def _prepare(self, params: Params, dtype) -> dict[str, Array]:
        names = self.param_names
        missing = [n for n in names if n not in params]
        extra = [n for n in params if n not in names]
        if missing or extra:
            raise KeyError(
                f"{type(self).__name__}.eval expects parameters {names}; "
                f"missing {missing}, unexpected {extra}"
            )
        p: dict[str, Array] = {}
        for q in self.params:
            v = jnp.asarray(params[q.name]).astype(dtype)
            if q.kind == "color" and v.ndim == 0:
                v = v[None]
            if q.kind == "lobes" and (v.ndim < 2 or v.shape[-1] != 4):
                raise JaxreflError(
                    f"parameter {q.name!r} must have shape (..., L, 4) rows (Cx, Cy, Cz, n); "
                    f"got {v.shape}"
                )
            p[q.name] = v
        return p

    def _align_ranks(
        self, p: dict[str, Array], wi: Array, wo: Array
    ) -> tuple[dict[str, Array], Array, Array]:
        """Give every input the same number of batch axes (leading singleton axes).

        Inputs may differ in batch rank ((3,) directions with (N,) parameters); padding them
        here once means no model relies on implicit rank promotion, which the test suite
        turns into an error.
        """
        trailing = {"scalar": 0, "color": 1, "lobes": 2}
        kinds = {q.name: q.kind for q in self.params}
        rank = max(wi.ndim - 1, wo.ndim - 1, *(v.ndim - trailing[kinds[n]] for n, v in p.items()))

        def pad(v: Array, core: int) -> Array:
            return v.reshape((1,) * (rank + core - v.ndim) + v.shape)

        p = {n: pad(v, trailing[kinds[n]]) for n, v in p.items()}
        return p, pad(wi, 1), pad(wo, 1)
