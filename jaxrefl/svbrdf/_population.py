"""Population priors: the capture's reliably fitted pixels as the prior of the others.

Where no photo saw a pixel's highlight, its lobe is not identified: a wide lobe with a large
F0 explains the photos as well as a narrow one or none, and the posterior's mass follows
the prior's *volume* along that ridge. Under the uniform default prior on a coloured F0 in
[0, 1]^3 (:func:`jaxrefl.posterior.default_priors`) most of that volume is bright coloured
lobes, so the posterior of such a pixel confidently reports a rough, bright lobe that the
data never showed (``benchmarks/predictive_coverage.py``: on a synthetic capture with grey
F0 the uncertainty map's 90% intervals of alpha then cover the truth on a minority of those
pixels).

:func:`population_priors` replaces the default priors of the lobe by empirical Bayes
estimates (Robbins 1956; Efron & Morris 1973) from the fitted values of every pixel the fit
gave an estimate (a finite optimum and noise scale), not only of the pixels whose Laplace
approximation it calls reliable. Whether a lobe is identified depends on the lobe itself
(a broad, dim lobe trades against the albedo; a narrow one between the photos is missed),
so the reliable pixels are a sample selected by the very parameters the prior describes:
their population sits where lobes are easy to see, and as a prior it pulls the pixels an
uncertainty map samples (exactly the unreliable ones) towards it, away from their truth.
The fitted values of all pixels carry each fit's estimation error, which widens the
population estimate (a conservative prior) instead of biasing it:

- ``specular`` (F0, grey or per channel): :class:`~jaxrefl.posterior.MultivariateNormal`
  with the fitted pixels' mean and covariance of the fitted F0, plus
  :data:`F0_FLOOR_STD`^2 on the diagonal (a numerical floor, kept small: see there), in
  units of the noise (``noise_ref`` the fitted pixels' median noise std: N(m, (s /
  s_ref)^2 S), the conjugate form the width sampler draws exactly). Channels that move
  together in the population (a grey dielectric, a gold's tint) keep doing so in the
  prior, which removes the volume of the coloured directions the data do not see.
- ``alpha``: :class:`~jaxrefl.posterior.LogNormal` with their median and log std (at least
  :data:`ALPHA_FLOOR_LOG_STD`).

The albedo keeps its uniform prior: the diffuse term is seen in every photo. Models without
a free per-pixel ``alpha`` (``lambert``, ``pooled``) keep the defaults. With fewer than
:data:`MIN_PIXELS` fitted pixels there is no population to estimate: the defaults again.
The population is one Gaussian: a capture of two very different materials, both flagged
where unseen, gets a prior that spans both (its covariance), not a mixture.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxrefl import fit
from jaxrefl import posterior as jp

from ._job_types import CaptureFit

__all__ = ["ALPHA_FLOOR_LOG_STD", "F0_FLOOR_STD", "MIN_PIXELS", "population_priors"]

# Reliable pixels below which the population is not estimated (a 3 x 3 covariance from
# fewer is mostly noise).
MIN_PIXELS = 30
# Std added to every F0 channel of the population prior: keeps its covariance positive
# definite where the fitted pixels' F0 does not vary (all at a bound, say). It is kept
# below the F0 a fit resolves: the fitted values' covariance already holds each fit's own
# estimation noise, and a wider floor costs dark lobes prior mass. Where the population is
# grey, F0 near 0 needs every channel's deviation from grey to stay above 0 (the box's
# corner), so the prior's mass at a grey level g below the floor shrinks like (g /
# floor)^2, which pushes an unseen dark lobe towards a brighter, rougher one.
F0_FLOOR_STD = 0.002
# Smallest log std of the alpha prior: a factor of 1.3 in roughness, the spread within one
# material's patches.
ALPHA_FLOOR_LOG_STD = 0.25


def population_priors(
    cf: CaptureFit, space: fit.ParamSpace | None = None
) -> tuple[dict[str, jp.Prior], dict[str, Any]]:
    """(priors by parameter name, summary) of the capture fit ``cf`` (module docstring).
    The priors are empty (the defaults apply) where the model has no free ``alpha`` or
    fewer than :data:`MIN_PIXELS` pixels were fitted; the summary says which and from how
    many pixels (JSON-ready)."""
    space = cf.model()[1] if space is None else space
    names = [b.name for b in space.blocks]
    if "alpha" not in names or "specular" not in names:
        return {}, {"source": "default", "why": "the model has no per-pixel lobe to pool"}
    theta = np.asarray(cf.theta, np.float64)
    noise = np.asarray(cf.maps["noise_std"], np.float64).reshape(-1)
    ok = np.all(np.isfinite(theta), -1) & np.isfinite(noise) & (noise > 0)
    n = int(np.sum(ok))
    if n < MIN_PIXELS:
        why = f"{n} fitted pixels (fewer than {MIN_PIXELS})"
        return {}, {"source": "default", "why": why, "pixels": n}
    x = np.asarray(space.natural_vector(jnp.asarray(theta[ok])), np.float64)
    spec = space.index("specular")
    f0 = x[:, spec]
    k = f0.shape[1]
    cov = np.atleast_2d(np.cov(f0, rowvar=False)) + F0_FLOOR_STD**2 * np.eye(k)
    cov = 0.5 * (cov + cov.T)
    s_ref = float(np.median(noise[ok]))
    mean = tuple(float(v) for v in f0.mean(0))
    f0_prior = jp.MultivariateNormal(mean, tuple(map(tuple, cov.tolist())), noise_ref=s_ref)
    log_a = np.log(x[:, space.index("alpha")].reshape(-1))
    a_prior = jp.LogNormal(
        float(np.exp(np.median(log_a))), max(float(np.std(log_a)), ALPHA_FLOOR_LOG_STD)
    )
    summary = {
        "source": "population",
        "pixels": n,
        "specular": {"mean": list(mean), "cov": cov.tolist(), "noise_ref": s_ref},
        "alpha": {"median": a_prior.median, "log_std": a_prior.log_std},
    }
    return {"specular": f0_prior, "alpha": a_prior}, summary
