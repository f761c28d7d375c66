"""Leave out the pixels (and lights) a scene does not need, before any solve.

A pixel enters the computation only when it can say something about reflectance. Each left
out pixel gets the first reason that applies:

============  ===========================================================================
reason        the pixel has ...
============  ===========================================================================
``masked``    ``mask`` False, or no finite observation with weight > 0
``shadowed``  fewer than ``min_obs`` lit observations (scale > 0, light above the horizon):
              a cast or attached shadow, or a light behind the surface
``saturated`` fewer than ``min_obs`` lit observations that are not saturated (censored +1,
              or obs >= ``saturation`` when given)
``no_signal`` no lit, unsaturated observation above ``noise_floor`` (all dark: nothing to
              fit but noise)
============  ===========================================================================

:func:`compact` *removes* those pixels from the arrays (the solver never sees them, unlike
a zero weight, which still costs a residual and Jacobian row every iteration), and then
removes the observation columns (lights) that no kept pixel can use. :meth:`Compacted.expand`
puts a fit of the compacted data back in place, with ``Status.MASKED`` and NaN parameters
for the pixels left out; :attr:`Compacted.counts` reports how many went for each reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import FitResult, PixelData, Status

__all__ = ["REASONS", "Compacted", "compact"]

REASONS = ("masked", "shadowed", "saturated", "no_signal")


@dataclass(frozen=True, eq=False)
class Compacted:
    """The pixels that are fitted, and what was left out.

    data:       the kept pixels (N_kept, K_kept, C)
    index:      (N_kept,) positions of the kept pixels in the input
    columns:    (K_kept,) observation columns kept
    reason:     (N,) "" for kept pixels, else one of :data:`REASONS`
    """

    data: PixelData
    index: np.ndarray
    columns: np.ndarray
    reason: np.ndarray
    n_obs_in: int = 0
    settings: dict = field(default_factory=dict)

    @property
    def n_in(self) -> int:
        return int(self.reason.shape[0])

    @property
    def counts(self) -> dict[str, int]:
        """Pixels kept, left out per reason, and observation columns kept / dropped."""
        out = {"pixels_in": self.n_in, "kept": int(self.index.size)}
        for r in REASONS:
            out[r] = int(np.sum(self.reason == r))
        out["columns_in"] = self.n_obs_in
        out["columns_kept"] = int(self.columns.size)
        return out

    def expand(self, result: FitResult) -> FitResult:
        """``result`` (a fit of :attr:`data`) on every input pixel; left-out pixels get
        ``Status.MASKED``, NaN theta/params/cost and 0 iterations and usable counts."""
        n = self.n_in
        idx = self.index

        def put(x, fill):
            x = np.asarray(x)
            out = np.full((n, *x.shape[1:]), fill, dtype=x.dtype)
            out[idx] = x
            return jnp.asarray(out)

        theta = put(result.theta, np.nan)
        return FitResult(
            result.space.to_natural(theta),
            theta,
            put(result.status, int(Status.MASKED)),
            put(result.cost, np.nan),
            put(result.iterations, 0),
            put(result.n_used, 0),
            result.space,
            result.model,
            result.backend,
        )


def compact(
    data: PixelData,
    mask: np.ndarray | None = None,
    *,
    min_obs: int = 1,
    saturation: float | None = None,
    noise_floor: float = 0.0,
) -> Compacted:
    """Remove the pixels of ``data`` (leading N axis) that a fit does not need (module
    docstring), then the observation columns no kept pixel uses.

    mask:        (N,) bool, False = not part of the scene (background, another object)
    min_obs:     observations a pixel needs (per channel entry; give the number of free
                 parameters of the model to be fitted)
    saturation:  observations >= this count as saturated (besides ``censored == +1``)
    noise_floor: an observation carries signal only above this value (same units as obs)
    """
    obs = np.asarray(data.obs)
    if obs.ndim != 3:
        raise JaxreflError(f"compact expects data of shape (N, K, C); got {obs.shape}")
    n, k, _ = obs.shape
    scale = np.asarray(data.scale)
    weight = np.asarray(data.weight)
    wi = np.asarray(data.wi)
    cens = np.asarray(data.censored)
    valid = np.isfinite(obs) & np.isfinite(scale) & np.isfinite(weight) & (weight > 0)
    valid &= np.all(np.isfinite(wi), axis=-1)[..., None]
    lit = valid & (scale > 0) & (wi[..., 2] > 0)[..., None]
    sat = cens > 0
    if saturation is not None:
        sat |= np.where(np.isfinite(obs), obs, 0.0) >= saturation
    good = lit & ~sat
    signal = good & (np.where(good, obs, -np.inf) > noise_floor)
    m = np.ones(n, bool) if mask is None else np.asarray(mask, bool).reshape(n)
    reason = np.full(n, "", dtype=object)
    count = lambda a: a.reshape(n, -1).sum(axis=1)  # noqa: E731
    checks = (
        ("masked", ~m | (count(valid) == 0)),
        ("shadowed", count(lit) < min_obs),
        ("saturated", count(good) < min_obs),
        ("no_signal", count(signal) == 0),
    )
    for name, bad in checks:
        reason[(reason == "") & bad] = name
    index = np.flatnonzero(reason == "")
    # Columns (lights) that light some kept pixel; censored ones still count as usable.
    used = np.any(lit[index], axis=(0, 2)) if index.size else np.zeros(k, bool)
    columns = np.flatnonzero(used)
    sub = jax.tree.map(lambda x: x[index][:, columns], data)
    return Compacted(
        sub,
        index,
        columns,
        reason.astype(str),
        int(k),
        {"min_obs": min_obs, "saturation": saturation, "noise_floor": noise_floor},
    )
