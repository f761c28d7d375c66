"""Unconstrained parametrisations: bijections u -> x and the parameter vector of a model.

Least-squares solvers work on an unconstrained vector ``theta`` (shape ``(*b, P)``); models
take natural parameters with ranges (albedo in [0, 1], alpha > 0, ...). Each parameter gets
an elementwise bijection from the real line onto its range:

=================  ======================================  ==============================
bijection           x = forward(u)                           dx/du = dforward(u)
=================  ======================================  ==============================
``Identity``        u                                        1
``Exp`` (``Log``)   lower + exp(u)                           exp(u)
``Softplus``        lower + log(1 + exp(u))                  sigmoid(u)
``ScaledSigmoid``   lower + (upper - lower) s,  s=sigmoid(u) (upper - lower) s (1 - s)
``UnitVector``      u / |u|          (3-vectors, directions) (I - x x^T) / |u|  (3 x 3)
=================  ======================================  ==============================

``inverse(x)`` first clips x into the open range (a bound itself has no finite preimage).

Defaults chosen by :class:`ParamSpace` from each :class:`~jaxrefl.brdf.Param`:

* widths, exponents and optical constants (``alpha``, ``alpha_u``, ``alpha_v``,
  ``exponent``, ``sigma``, ``k``, ``eta``) and any parameter with only a finite lower bound:
  ``Exp`` with that lower bound. The log scale matches how these act (a highlight's width
  spans decades). The model's upper bound is *not* enforced (alpha > 1 is still a valid
  GGX; :meth:`ParamSpace.at_bound` reports a value beyond it): if the user gives a finite
  upper bound in ``bounds``, ``ScaledSigmoid`` is used instead.
* every other parameter with a finite range (``albedo``, ``specular`` in [0, 1]):
  ``ScaledSigmoid``.
* Lafortune ``lobes`` rows (Cx, Cy, Cz, n): ``Identity`` for the C's, ``Exp`` for n > 0.
* parameters with no finite lower bound: ``Identity``.

User ``bounds`` override the model's range; ``fixed`` parameters leave the vector and are
supplied as constants; ``transforms`` override the choice per parameter.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF, Param

__all__ = [
    "Bijection",
    "Exp",
    "Identity",
    "Log",
    "ParamSpace",
    "ScaledSigmoid",
    "Softplus",
    "UnitVector",
]

# inverse() of a one-sided bijection floors x - lower at this absolute gap (times
# 1 + |lower|): closer than that a parameter is indistinguishable from its bound for every
# model here, and exp(u) >= 1e-6 keeps the derivative large enough for a solver to move it.
_GAP_FLOOR = 1e-6
# inverse() of ScaledSigmoid clips the unit value s into [1e-6, 1 - 1e-6]: 1 - 1e-6 is still
# representable in float32 (spacing 6e-8 near 1), so u = logit(s) stays finite (|u| <= 13.8).
_SIGMOID_EPS = 1e-6

# Parameters acting on a log scale (see the module docstring).
LOG_SCALE_NAMES = frozenset({"alpha", "alpha_u", "alpha_v", "exponent", "sigma", "k", "eta"})


class Bijection(eqx.Module):
    """An elementwise bijection from the real line onto (lower, upper)."""

    @property
    def elementwise(self) -> bool:
        return True

    @property
    def range(self) -> tuple[float, float]:
        """The natural range (lower, upper) of forward()."""
        return (-math.inf, math.inf)

    def forward(self, u: Float[Array, "*b"]) -> Float[Array, "*b"]:
        raise NotImplementedError

    def inverse(self, x: Float[Array, "*b"]) -> Float[Array, "*b"]:
        raise NotImplementedError

    def dforward(self, u: Float[Array, "*b"]) -> Float[Array, "*b"]:
        """dx/du, elementwise."""
        raise NotImplementedError


class Identity(Bijection):
    """x = u."""

    def forward(self, u):
        return u

    def inverse(self, x):
        return x

    def dforward(self, u):
        return jnp.ones_like(u)


class Exp(Bijection):
    """x = lower + exp(u), x in (lower, inf): for widths, exponents, optical constants."""

    lower: float = 0.0

    @property
    def range(self):
        return (self.lower, math.inf)

    def forward(self, u):
        return self.lower + jnp.exp(u)

    def inverse(self, x):
        # Clip into the open range: floor the gap to the bound (see _GAP_FLOOR).
        gap = jnp.maximum(x - self.lower, _GAP_FLOOR * (1.0 + abs(self.lower)))
        return jnp.log(gap)

    def dforward(self, u):
        return jnp.exp(u)


Log = Exp  # named after its inverse, u = log(x - lower)


class Softplus(Bijection):
    """x = lower + log(1 + exp(u)): like Exp near the bound, like the identity far from it."""

    lower: float = 0.0

    @property
    def range(self):
        return (self.lower, math.inf)

    def forward(self, u):
        return self.lower + jax.nn.softplus(u)

    def inverse(self, x):
        # Clip into the open range (see _GAP_FLOOR); log(expm1(y)) written stably for large y.
        y = jnp.maximum(x - self.lower, _GAP_FLOOR * (1.0 + abs(self.lower)))
        return y + jnp.log(-jnp.expm1(-y))

    def dforward(self, u):
        return jax.nn.sigmoid(u)


class ScaledSigmoid(Bijection):
    """x = lower + (upper - lower) sigmoid(u), x in (lower, upper); both bounds finite."""

    lower: float = 0.0
    upper: float = 1.0

    def __check_init__(self):
        if not (math.isfinite(self.lower) and math.isfinite(self.upper)):
            raise JaxreflError(f"ScaledSigmoid needs finite bounds, got {self.lower, self.upper}")
        if not self.upper > self.lower:
            raise JaxreflError(f"ScaledSigmoid needs upper > lower, got {self.lower, self.upper}")

    @property
    def range(self):
        return (self.lower, self.upper)

    def forward(self, u):
        return self.lower + (self.upper - self.lower) * jax.nn.sigmoid(u)

    def inverse(self, x):
        s = (x - self.lower) / (self.upper - self.lower)
        # Clip into the open interval (see _SIGMOID_EPS).
        s = jnp.clip(s, _SIGMOID_EPS, 1.0 - _SIGMOID_EPS)
        return jnp.log(s) - jnp.log1p(-s)

    def dforward(self, u):
        s = jax.nn.sigmoid(u)
        return (self.upper - self.lower) * s * (1.0 - s)


class UnitVector(Bijection):
    """x = u / |u| for 3-vectors (directions, e.g. a light direction in later stages).

    Not elementwise: ``jacobian(u)`` is the 3 x 3 matrix (I - x x^T) / |u|. The map has a
    gauge freedom: every positive multiple of u gives the same x, so J^T J of a problem in u
    is singular along u. Levenberg-Marquardt handles it through its damping (the step along
    the null direction is zero, lam * I keeps the system positive definite); report
    conditioning in x, not u. ``inverse`` picks the gauge |u| = 1. A zero u maps to +z.
    """

    @property
    def elementwise(self) -> bool:
        return False

    @property
    def range(self):
        return (-1.0, 1.0)

    def forward(self, u):
        n2 = jnp.sum(u * u, axis=-1, keepdims=True)
        ok = n2 > 0
        # u = 0 has no direction; +z is the one that is always valid (gradient-safe swap).
        u_safe = jnp.where(ok, u, jnp.asarray([0.0, 0.0, 1.0], dtype=u.dtype))
        return u_safe / jnp.sqrt(jnp.where(ok, n2, 1.0))

    def inverse(self, x):
        return self.forward(x)

    def dforward(self, u):
        raise JaxreflError("UnitVector is not elementwise; use UnitVector.jacobian(u) (3 x 3)")

    def jacobian(self, u: Float[Array, "*b 3"]) -> Float[Array, "*b 3 3"]:
        x = self.forward(u)
        # |u| floored at the smallest normal: u = 0 (mapped to +z) gets a finite Jacobian.
        n = jnp.sqrt(jnp.maximum(jnp.sum(u * u, axis=-1), jnp.finfo(u.dtype).tiny))
        eye = jnp.eye(3, dtype=u.dtype)
        outer = x[..., :, None] * x[..., None, :]
        return (eye - outer) / n[..., None, None]


class _Run(eqx.Module):
    """A contiguous run of theta entries [start, stop) sharing one bijection."""

    start: int = eqx.field(static=True)
    stop: int = eqx.field(static=True)
    bijection: Bijection
    lower: float = eqx.field(static=True)  # natural bounds reported for these entries
    upper: float = eqx.field(static=True)


class _Block(eqx.Module):
    """One free parameter: its runs in theta and the per-pixel natural shape."""

    name: str = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    shape: tuple[int, ...] = eqx.field(static=True)
    start: int = eqx.field(static=True)
    stop: int = eqx.field(static=True)
    runs: tuple[_Run, ...]
    grey: bool = eqx.field(default=False, static=True)  # one entry shared by all channels


def _channel_labels(channels: int) -> tuple[str, ...]:
    return ("R", "G", "B") if channels == 3 else tuple(f"c{i}" for i in range(channels))


def _natural_shape(q: Param, channels: int) -> tuple[int, ...]:
    if q.kind == "scalar":
        return ()
    if q.kind == "color":
        return (channels,)
    return (len(np.atleast_2d(np.asarray(q.default))), 4)


def _default_bijection(q: Param, lo: float, hi: float, user_upper: bool) -> Bijection:
    fin_lo, fin_hi = math.isfinite(lo), math.isfinite(hi)
    if q.name in LOG_SCALE_NAMES and not (user_upper and fin_lo and fin_hi):
        return Exp(lo) if fin_lo else Identity()
    if fin_lo and fin_hi:
        return ScaledSigmoid(lo, hi)
    return Exp(lo) if fin_lo else Identity()


class ParamSpace(eqx.Module):
    """The free parameters of ``model`` as one unconstrained vector theta of length P.

    Order: the model's parameter order, minus ``fixed``; colour parameters contribute C
    entries (channels R, G, B for C = 3, else c0, c1, ...), scalars one, Lafortune lobes 4 per
    lobe. ``labels`` names each entry: ``("albedo.R", ..., "specular.B", "alpha")``.

    Fixed values are global constants (the same for every pixel); a colour given as a scalar
    is broadcast to C channels. ``grey`` names colour parameters fitted as one value shared
    by every channel (e.g. a dielectric's specular F0): one entry, labelled by the name.
    """

    model: BRDF
    channels: int = eqx.field(static=True)
    channel_names: tuple[str, ...] = eqx.field(static=True)
    blocks: tuple[_Block, ...]
    fixed: dict[str, Array]
    size: int = eqx.field(static=True)
    labels: tuple[str, ...] = eqx.field(static=True)

    def __init__(
        self,
        model: BRDF,
        channels: int = 3,
        bounds: Mapping[str, tuple[float, float]] | None = None,
        fixed: Mapping[str, ArrayLike] | None = None,
        transforms: Mapping[str, Bijection] | None = None,
        channel_names: tuple[str, ...] | None = None,
        grey: tuple[str, ...] | list[str] = (),
    ):
        bounds = dict(bounds or {})
        grey = tuple(grey)
        for g in grey:
            if g not in model.param_names or model.param_spec(g).kind != "color":
                raise KeyError(f"grey names {g!r}, which is not a colour parameter of the model")
        fixed = dict(fixed or {})
        transforms = dict(transforms or {})
        names = model.param_names
        for what, d in (("bounds", bounds), ("fixed", fixed), ("transforms", transforms)):
            unknown = [n for n in d if n not in names]
            if unknown:
                raise KeyError(f"{what} names {unknown} are not parameters of the model {names}")
        if channel_names is None:
            channel_names = _channel_labels(channels)
        if len(channel_names) != channels:
            raise JaxreflError(f"{channels} channels but channel_names {channel_names}")
        self.model = model
        self.channels = int(channels)
        self.channel_names = tuple(str(c) for c in channel_names)

        blocks, labels, start = [], [], 0
        for q in model.params:
            if q.name in fixed:
                continue
            shape = _natural_shape(q, channels)
            is_grey = q.name in grey
            n = 1 if is_grey else int(np.prod(shape, dtype=int))
            lo, hi = (float(v) for v in bounds.get(q.name, (q.lower, q.upper)))
            if not hi > lo:
                raise JaxreflError(f"bounds for {q.name!r} must satisfy lower < upper: {lo, hi}")
            runs = []
            if q.name in transforms:
                bij = transforms[q.name]
                if not bij.elementwise and n != 3:
                    raise JaxreflError(f"{type(bij).__name__} needs a 3-entry parameter: {q.name}")
                b_lo, b_hi = bij.range
                runs.append(_Run(start, start + n, bij, max(lo, b_lo), min(hi, b_hi)))
            elif q.kind == "lobes":
                for j in range(shape[0]):
                    s = start + 4 * j
                    runs.append(_Run(s, s + 3, Identity(), lo, hi))
                    runs.append(_Run(s + 3, s + 4, Exp(0.0), 0.0, hi))
            else:
                bij = _default_bijection(q, lo, hi, user_upper=q.name in bounds)
                b_lo, b_hi = bij.range
                runs.append(_Run(start, start + n, bij, max(lo, b_lo), min(hi, b_hi)))
            blocks.append(_Block(q.name, q.kind, shape, start, start + n, tuple(runs), is_grey))
            labels.extend([q.name] if is_grey else self._labels_for(q, shape))
            start += n
        self.blocks = tuple(blocks)
        self.size = start
        self.labels = tuple(labels)
        fx = {}
        for q in model.params:
            if q.name in fixed:
                v = jnp.asarray(fixed[q.name])
                if not jnp.issubdtype(v.dtype, jnp.floating):
                    v = v.astype(jnp.float32)
                # A fixed value is used as given: it must be a finite number.
                if not isinstance(v, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(v))):
                    raise JaxreflError(
                        f"fixed[{q.name!r}] = {np.asarray(v).tolist()} is not finite; give a "
                        f"finite value in [{q.lower}, {q.upper}]"
                    )
                shape = _natural_shape(q, channels)
                fx[q.name] = jnp.broadcast_to(v, shape) if v.ndim == 0 else v
        self.fixed = fx

    def _labels_for(self, q: Param, shape: tuple[int, ...]) -> list[str]:
        if q.kind == "scalar":
            return [q.name]
        if q.kind == "color":
            return [f"{q.name}.{c}" for c in self.channel_names]
        return [f"{q.name}[{j}].{c}" for j in range(shape[0]) for c in ("Cx", "Cy", "Cz", "n")]

    # ------------------------------------------------------------------ structure
    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(b.name for b in self.blocks)

    @property
    def fixed_names(self) -> tuple[str, ...]:
        return tuple(self.fixed)

    def index(self, name: str) -> slice:
        """The slice of theta holding parameter ``name``."""
        for b in self.blocks:
            if b.name == name:
                return slice(b.start, b.stop)
        raise KeyError(f"{name!r} is not a free parameter; free: {self.free_names}")

    @property
    def elementwise(self) -> bool:
        """Whether every bijection is elementwise (then :meth:`dnatural` is defined)."""
        return all(r.bijection.elementwise for b in self.blocks for r in b.runs)

    @property
    def lower(self) -> np.ndarray:
        """(P,) natural lower bound of each entry (user bounds, else the model's range)."""
        return np.concatenate([[r.lower] * (r.stop - r.start) for b in self.blocks for r in b.runs])

    @property
    def upper(self) -> np.ndarray:
        """(P,) natural upper bound of each entry (not enforced by ``Exp``; see module doc)."""
        return np.concatenate([[r.upper] * (r.stop - r.start) for b in self.blocks for r in b.runs])

    # ------------------------------------------------------------------ maps
    def natural_vector(self, theta: Float[Array, "*b P"]) -> Float[Array, "*b P"]:
        """The natural value of every free entry, in the order of :attr:`labels`."""
        self._check(theta)
        runs = [r for b in self.blocks for r in b.runs]
        parts = [r.bijection.forward(theta[..., r.start : r.stop]) for r in runs]
        return jnp.concatenate(parts, axis=-1) if parts else theta

    def dnatural(self, theta: Float[Array, "*b P"]) -> Float[Array, "*b P"]:
        """d natural / d theta per entry (the diagonal of :meth:`jacobian_natural`).

        Defined when every bijection is elementwise (all defaults are); a ``UnitVector``
        parameter raises ValueError: use :meth:`jacobian_natural` then.
        """
        self._check(theta)
        if not self.elementwise:
            raise JaxreflError("ParamSpace holds a non-elementwise bijection; use jacobian_natural")
        runs = [r for b in self.blocks for r in b.runs]
        parts = [r.bijection.dforward(theta[..., r.start : r.stop]) for r in runs]
        return jnp.concatenate(parts, axis=-1) if parts else theta

    def jacobian_natural(self, theta: Float[Array, "*b P"]) -> Float[Array, "*b P P"]:
        """d natural_vector / d theta, (P, P) per pixel (block diagonal)."""
        jac = jax.jacfwd(self.natural_vector)
        return jnp.vectorize(jac, signature="(p)->(p,p)")(theta)

    def to_natural(self, theta: Float[Array, "*b P"]) -> dict[str, Array]:
        """Natural parameters for ``model.eval``: scalars (*b,), colours (*b, C), lobes
        (*b, L, 4); fixed parameters broadcast to the batch shape, in theta's dtype."""
        x = self.natural_vector(theta)
        batch = theta.shape[:-1]
        out = {}
        for q in self.model.params:
            if q.name in self.fixed:
                v = self.fixed[q.name].astype(theta.dtype)
                out[q.name] = jnp.broadcast_to(v, (*batch, *v.shape))
        for b in self.blocks:
            v = x[..., b.start : b.stop]
            if b.grey:  # one entry shared by the C channels
                v = jnp.broadcast_to(v, (*batch, *b.shape))
            out[b.name] = v.reshape((*batch, *b.shape))
        return {q.name: out[q.name] for q in self.model.params}

    def from_natural(self, params: Mapping[str, ArrayLike], dtype=None) -> Float[Array, "*b P"]:
        """theta for natural ``params`` (clipped into the open ranges first).

        Shapes as in :meth:`to_natural` (a colour may also be a scalar, (*b,) is *not*
        accepted for colours: give (*b, 1) to broadcast over channels). Missing free
        parameters take the model's default; fixed parameters and unknown keys are ignored.
        """
        vals, batches = {}, []
        for b in self.blocks:
            q = self.model.param_spec(b.name)
            v = jnp.asarray(params[b.name] if b.name in params else q.default)
            vals[b.name] = v
            batches.append(v.shape[: v.ndim - len(b.shape)] if v.ndim >= len(b.shape) else ())
        if dtype is None:
            floats = [v.dtype for v in vals.values() if jnp.issubdtype(v.dtype, jnp.floating)]
            dtype = jnp.result_type(*floats) if floats else jnp.float32
        batch = tuple(np.broadcast_shapes(*batches)) if batches else ()
        parts = []
        for b in self.blocks:
            v = jnp.broadcast_to(vals[b.name].astype(dtype), (*batch, *b.shape))
            if b.grey:  # a shared channel value: the mean of the given colour
                v = jnp.mean(v, axis=-1, keepdims=True)
            v = v.reshape((*batch, b.stop - b.start))
            for r in b.runs:
                parts.append(r.bijection.inverse(v[..., r.start - b.start : r.stop - b.start]))
        if not parts:
            return jnp.zeros((*batch, 0), dtype=dtype)
        return jnp.concatenate(parts, axis=-1)

    def default_theta(self, dtype=jnp.float32) -> Float[Array, " P"]:
        """theta at the model's default parameter values."""
        return self.from_natural({}, dtype=dtype)

    def off_bounds(self, theta: Float[Array, "*b P"], max_u: float = 3.0) -> Float[Array, "*b P"]:
        """theta with every sigmoid-mapped entry (:class:`ScaledSigmoid`: a range bounded on
        both sides) clipped to [-max_u, max_u] in the unconstrained space: a start moved off
        the bounds. A fit that ends on a bound leaves the logit far out, where the sigmoid is
        flat and a solver or sampler started there has no usable gradient; the default 3 is
        4.7% of the range from either edge, where the sigmoid's slope is still 0.045 of its
        peak. Other maps (``Exp`` for alpha, whose bounds are a check, not the map) keep
        their values."""
        theta = jnp.asarray(theta)
        bounded = np.zeros(self.size, bool)
        for b in self.blocks:
            for r in b.runs:
                if isinstance(r.bijection, ScaledSigmoid):
                    bounded[r.start : r.stop] = True
        if not bounded.any():
            return theta
        lim = np.where(bounded, max_u, np.inf).reshape((1,) * (theta.ndim - 1) + (-1,))
        return jnp.clip(theta, jnp.asarray(-lim, theta.dtype), jnp.asarray(lim, theta.dtype))

    def at_bound(self, theta: Float[Array, "*b P"], rtol: float = 1e-3) -> Bool[Array, "*b P"]:
        """Entries within ``rtol`` of a bound, or beyond it.

        The tolerance is relative to the width of a finite range, else to max(|bound|, 1):
        with the default 1e-3, albedo in [0, 1] is flagged below 0.001 or above 0.999, and
        alpha (bounds [1e-4, 1], Exp) below 1.1e-3 or above 0.999.
        """
        x = self.natural_vector(theta)
        lead = (1,) * (x.ndim - 1)
        lo = jnp.asarray(self.lower, dtype=x.dtype).reshape((*lead, -1))
        hi = jnp.asarray(self.upper, dtype=x.dtype).reshape((*lead, -1))
        finite_lo, finite_hi = jnp.isfinite(lo), jnp.isfinite(hi)
        width = jnp.where(finite_lo & finite_hi, hi - lo, 0.0)
        mag_lo = jnp.maximum(jnp.abs(jnp.where(finite_lo, lo, 0.0)), 1.0)
        mag_hi = jnp.maximum(jnp.abs(jnp.where(finite_hi, hi, 0.0)), 1.0)
        scale_lo = jnp.where(width > 0, width, mag_lo)
        scale_hi = jnp.where(width > 0, width, mag_hi)
        near_lo = finite_lo & (x - lo <= rtol * scale_lo)
        near_hi = finite_hi & (hi - x <= rtol * scale_hi)
        return near_lo | near_hi

    def _check(self, theta) -> None:
        if theta.shape[-1:] != (self.size,):
            raise JaxreflError(
                f"theta must have a trailing axis of length P = {self.size} {self.labels}, "
                f"got shape {theta.shape}"
            )
