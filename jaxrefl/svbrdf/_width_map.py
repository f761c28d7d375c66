"""Each pixel's own lobe width around the ``pooled`` model's shared one: partial pooling.

The ``pooled`` model (:mod:`jaxrefl.svbrdf._pooled`) gives every pixel one GGX width alpha,
the one that predicts held-out photos best. Its posterior is conditional on that width: a
pixel whose surface is rougher or smoother than the capture's width gets F0 and albedo
intervals for the wrong lobe, and no interval of its own width at all. An uncertainty map
is a statement about each pixel's parameters, so it relaxes the shared width to a
population (a hierarchical model; Gelman et al. 2013, *Bayesian Data Analysis*, ch. 5):

    log alpha_i ~ N(c, tau^2)

tau = 0 is the pooled model; tau -> inf is a free per-pixel width (``ggx_rgb``). Each
pixel's own estimate comes from the per-pixel model: a ``ggx_rgb`` fit of the capture under
the same light, whose Laplace approximation gives l_i = log alpha_i-hat with variance V_i
(the delta method from its ``alpha_std``; V_i = inf where it has none, or where the width
sits at a bound of its range: a one-sided statement). Given the population, l_i ~ N(c,
tau^2 + V_i), and each pixel's width is the normal-normal posterior

    log alpha_i | data ~ N(m_i, 1 / P_i),   P_i = 1 / V_i + 1 / tau^2,
    m_i = (l_i / V_i + c / tau^2) / P_i,

plus the shared width's own Laplace variance (the pooled fit's ``alpha_std``). The
empirical-Bayes (c, tau) maximise the marginal likelihood over the pixels (Efron & Morris
1973; :func:`population`), but that deconvolution assumes V_i independent of alpha_i, and
flash photos see narrow lobes sharply and wide ones hardly; so c is the informing pixels'
median estimate and tau is at least their estimates' robust spread, one material's spread
(:data:`jaxrefl.svbrdf._population.ALPHA_FLOOR_LOG_STD`) and |c - log alpha_shared| / 1.645
(:func:`population_bounds` gives the reasons). Since the precision follows the width, each
pixel is shrunk towards the centre of the pixels about as precise as it is, c_i: the median
estimate of its group of :data:`GROUPS` by V_i's quantiles (the group-linear estimates of
Weinstein et al. 2018). A rough lobe that a flash photo hardly sees is shrunk towards the
other hardly seen lobes, not towards the sharply seen narrow ones (on ``dim_many`` of
``benchmarks/capture_family.py`` the one centre of all informing pixels sat at about half
the width of its roughest pixels). A pixel no photo's highlight reached (V_i = inf) gets the
population's width; one that sees its lobe its own, shrunk towards its group's centre by
its uncertainty.

The other parameters follow their pixel's width. The albedo and F0 follow it along the
pixel's conditional optimum x_i(alpha): given a width, ``pooled``'s per-pixel problem is a
non-negative least-squares fit of two basis images (:mod:`jaxrefl.svbrdf._pooled`), solved
exactly and cheaply at any width. The map's means move by x_i(exp m_i) - x_i(alpha_shared)
on the curve the pooled fit's prior on F0 regularises (it passes through the pooled fit's
optimum), and the width's 90% range [q05_i, q95_i] spans x_i(q05_i) .. x_i(q95_i) on the
curve without that prior, which adds to the interval's ends in quadrature (as a sum of
independent spreads does):

    lower_i = mean_i - sqrt((mean_i - q05_i)^2 + (x_i(exp m_i) - min x_i)^2), upper alike,

the min and max over the three widths on the curve without the prior and the median width on
the curve with it (so the interval also spans the gap between the two curves). The prior is
left out of the spread because it is the population of F0 fitted at the shared width: at
another width the pixels' F0 lie elsewhere, and held to it the curve hardly moves
(``dim_many`` of ``benchmarks/capture_family.py``: F0's intervals then miss its rough
pixels' F0 far more often than one time in ten). The curve is far from straight over a
population's spread: along the ridge a flash photo of the highlight's peak leaves, F0 scales
with alpha^2 (D_GGX(h = n) = 1 / (pi alpha^2)), and in a lobe's tail the other way; a first-
order line through the shared width misses a rough pixel's F0 by a factor of several there.
The other parameters (the noise scale) move, to first order, on the line from the pooled
fit's to the per-pixel fit's at the shrinkage weight w_i = (1 / V_i) / P_i, and gain v_i^2 /
P_i in variance, with v_i = d x_i / d log alpha at the shared width (the Gauss-Newton terms
of :mod:`jaxrefl.svbrdf._width_laplace`: v_i = H_i^-1 J_i^T j_i). The map's 5% and 95% quantiles
move and widen alike (as :func:`jaxrefl.svbrdf._light_map.widen_for_light` does for the
light), inside the parameters' box. The draws in ``posterior.nc`` stay the pooled
posterior's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._job import fit_capture
from ._models import ALPHA_RANGE
from ._pooled import _censored_nnls, _columns, _lobe_basis, _obs_major
from ._population import ALPHA_FLOOR_LOG_STD

__all__ = [
    "GROUPS",
    "PER_PIXEL",
    "TAU_GRID",
    "TRIM",
    "WidthSpread",
    "group_centres",
    "pixel_widths",
    "population",
    "population_bounds",
    "relax_shared_width",
]

#: The per-pixel model whose fit gives each pixel's own width (``pooled`` is this model with
#: one width for the capture).
PER_PIXEL = "ggx_rgb"
#: Candidate population std of log alpha: from a width shared to round-off (0.01, 1%) to
#: 1.5 (90% of the widths over a factor of 140, past which a population pools nothing).
TAU_GRID = np.geomspace(0.01, 1.5, 201)
#: Standard deviations past which a pixel's estimate is left out of the population's fit
#: (module docstring; :func:`population`), and the rounds of leaving out.
TRIM = 4.0
_TRIM_ROUNDS = 5
#: Groups of informing pixels by the variance of their estimate, each with its own centre
#: (module docstring), and the fewest pixels a group holds (fewer groups where there are
#: fewer pixels).
GROUPS = 5
_GROUP_PIXELS = 30
#: Relative distance from a bound of alpha's range within which a per-pixel width is a
#: one-sided statement (the width at or past the bound), not an estimate.
_AT_BOUND = 0.01
_TILE = 16384  # pixels a tile of the Gauss-Newton terms (bounds their memory)
# Ridge relative to the curvature's largest diagonal entry: keeps the solve finite where a
# direction of theta is unseen (a lobe no photo saw); it gets no share of the width.
_RIDGE = 1e-9
_Z95 = 1.6448536269514722  # the standard normal's 95% quantile


@dataclass(frozen=True)
class WidthSpread:
    """The population of lobe widths around the shared one (module docstring).

    alpha:     the pooled fit's shared width
    centre:    exp(c), the population's median width (empirical Bayes)
    tau:       the population std of log alpha (empirical Bayes)
    log_std_shared: the shared width's own Laplace std of log alpha
    pixels:    pixels whose own estimate entered the population's
    mean, std, q05, q95: (N,) each pixel's width (NaN where the fit has no estimate)
    move:      (N, P) the move of each parameter's mean, natural units
    var:       (N, P) the variance each parameter gains, natural units
    down, up:  (N, P) the width's share of the distance from the mean to the 5% and the 95%
               quantile, natural units (NaN: from ``var`` as a normal's)
    """

    alpha: float
    centre: float
    tau: float
    log_std_shared: float
    pixels: int
    mean: np.ndarray
    std: np.ndarray
    q05: np.ndarray
    q95: np.ndarray
    move: np.ndarray
    var: np.ndarray
    down: np.ndarray
    up: np.ndarray

    def summary(self) -> dict[str, Any]:
        """JSON-ready: the population and how far the pixels' widths spread."""
        ok = np.isfinite(self.mean)
        med = float(np.median(self.mean[ok])) if ok.any() else None
        return {
            "method": f"partial pooling: {PER_PIXEL}'s widths shrunk to their population",
            "alpha_shared": self.alpha,
            "alpha_centre": self.centre,
            "log_alpha_tau": self.tau,
            "log_alpha_std_shared": self.log_std_shared,
            "pixels_informing": self.pixels,
            "alpha_median": med,
        }


@eqx.filter_jit
def _slopes(residual, theta, data):
    """(N, P) v_i = H_i^-1 J_i^T j_i (module docstring) at the shared width: minus the slope
    of each pixel's conditional optimum in theta per unit of log alpha. The terms of
    :func:`jaxrefl.svbrdf._width_laplace.width_terms`, but for every pixel the map holds: a ridge
    in place of its refusal of a curvature that is not positive definite, so a pixel that
    saw only part of its lobe still gets the width's share in the directions it saw (the
    sampled pixels are mostly such)."""
    log_alpha = jnp.log(residual.space.fixed["alpha"])

    def pixel(t, d):
        # the pixel's noise scale multiplies J and j alike and cancels in v
        ok = residual.usable(d) & (d.censored == 0)
        sw = jnp.where(ok, jnp.sqrt(jnp.where(ok, d.weight, 0.0)), 0.0).reshape(-1)
        obs = jnp.where(ok, d.obs, 0.0).reshape(-1)

        def r_of(th, la):
            pred = residual.predict(th, d, replace={"alpha": jnp.exp(la)}).reshape(-1)
            return sw * (pred - obs)

        la = log_alpha.astype(t.dtype)
        jac = jax.jacfwd(r_of, argnums=0)(t, la)
        _, j_t = jax.jvp(lambda x: r_of(t, x), (la,), (jnp.ones_like(la),))
        h_mat = jac.T @ jac
        h_mat = h_mat + _RIDGE * jnp.max(jnp.diag(h_mat)) * jnp.eye(t.shape[0], dtype=t.dtype)
        v = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(h_mat), True), jac.T @ j_t)
        return jnp.where(jnp.all(jnp.isfinite(v)), v, jnp.nan)

    return jax.vmap(pixel)(theta, data)


@jax.jit
def _conditional(alpha, data, prior_w, prior_mu):
    """(N, 2C): each pixel's albedo and F0 (C channels each) of ``pooled``'s fit
    (:mod:`jaxrefl.svbrdf._pooled`) at the pixel's own width ``alpha`` (N,): non-negative
    least squares over every usable photo, censored rows one-sided, and F0's Gaussian prior
    N(prior_mu, (sigma / prior_w)^2) per channel as one more row (prior_w = sigma / prior
    std; 0: none), so that the curve passes through the pooled fit's optimum."""
    n, _k, c = data.obs.shape
    y, cens, base, b0 = _columns(data)
    b1 = _obs_major(_lobe_basis(alpha[:, None], data))
    pw, pm = jnp.repeat(prior_w, n)[None], jnp.repeat(prior_w * prior_mu, n)[None]
    a, u = _censored_nnls(
        jnp.concatenate([b0, jnp.zeros_like(pw)]),
        jnp.concatenate([b1, pw]),
        jnp.concatenate([y, pm]),
        jnp.concatenate([cens, jnp.zeros_like(cens[:1])]),
        jnp.concatenate([base.astype(y.dtype), jnp.ones_like(pw)]),
    )
    return jnp.concatenate([a.reshape(c, n).T, u.reshape(c, n).T], axis=1)


def _curve(cf, data, widths: tuple[np.ndarray, ...], prior: bool) -> list[np.ndarray]:
    """:func:`_conditional` at each (N,) array of ``widths``, under ``cf``'s pooled prior
    on F0 where ``prior``, in tiles of :data:`_TILE`."""
    n, c = widths[0].shape[0], data.obs.shape[-1]
    dtype = np.asarray(data.obs).dtype
    pooled = cf.pooled
    prior_w, prior_mu = np.zeros(c), np.zeros(c)
    if prior and pooled is not None and pooled.sigma is not None and len(pooled.prior_std) == c:
        sd = np.asarray(pooled.prior_std, np.float64)
        prior_w = np.where(sd > 0, float(pooled.sigma) / np.where(sd > 0, sd, 1.0), 0.0)
        prior_mu = np.asarray(pooled.prior_mean, np.float64)
    pw, pm = jnp.asarray(prior_w, dtype), jnp.asarray(prior_mu, dtype)
    out = [np.full((n, 2 * c), np.nan) for _ in widths]
    for a in range(0, n, _TILE):
        b = min(a + _TILE, n)
        blk = jax.tree.map(lambda x, a=a, b=b: x[a:b], data)
        for o, wd in zip(out, widths, strict=True):
            # a pixel without a width gets the shared one's; its row is masked by the caller
            o[a:b] = np.asarray(_conditional(jnp.asarray(wd[a:b], dtype), blk, pw, pm))
    return out


def population(
    est: np.ndarray, var: np.ndarray, grid: np.ndarray = TAU_GRID
) -> tuple[float, float]:
    """(c, tau): the empirical-Bayes centre and std of the population of log alpha, from
    the pixels' estimates ``est`` with variances ``var`` (inf: no information): est_i ~
    N(c, tau^2 + var_i) (the normal hierarchical model; Gelman et al. 2013, sec. 5.4). tau
    maximises the marginal likelihood over ``grid``, c at its precision-weighted mean for
    each. An estimate far out in the tails (a fit at a wrong optimum) must not set the
    population's spread: estimates more than :data:`TRIM` standard deviations from the
    centre are left out and the fit repeated (which trims 0.006% of a normal population).
    (nan, the grid's first value) where no pixel informs the width."""
    ok = np.isfinite(est) & np.isfinite(var) & (var > 0)
    if not ok.any():
        return float("nan"), float(grid[0])
    e_all, v_all = est[ok], var[ok]
    keep = np.ones(e_all.shape, bool)
    c_k, tau_k = float(np.median(e_all)), float(grid[0])
    for _ in range(_TRIM_ROUNDS):
        e, tot = e_all[keep][:, None], v_all[keep][:, None] + grid[None, :] ** 2
        c = np.sum(e / tot, axis=0) / np.sum(1.0 / tot, axis=0)
        ll = -0.5 * np.sum(np.log(tot) + (e - c[None, :]) ** 2 / tot, axis=0)
        k = int(np.argmax(ll))
        c_k, tau_k = float(c[k]), float(grid[k])
        inside = np.abs(e_all - c_k) <= TRIM * np.sqrt(v_all + tau_k**2)
        if np.array_equal(inside, keep) or not inside.any():
            break
        keep = inside
    return c_k, tau_k


def population_bounds(est: np.ndarray, var: np.ndarray, shared: float) -> tuple[float, float]:
    """(c, tau) of the map's width population from the per-pixel estimates ``est`` with
    variances ``var`` (inf: no information) and the pooled fit's log width ``shared``.

    :func:`population`'s deconvolution assumes each estimate's variance is independent of
    the width it estimates. Flash photos break that: they see a narrow lobe sharply and a
    wide one hardly (on a dim or rough capture V_i grows by two orders of magnitude from the
    narrowest to the widest tercile), so the deconvolved population collapses onto the
    narrow lobes, and precision weights pull its centre there (the dependence of means on
    variances of Weinstein et al. 2018, *JASA* 113:698, "Group-linear empirical Bayes
    estimates for a heteroscedastic normal mean"). So the centre is the informing pixels'
    median estimate, unweighted, and tau is the largest of: the empirical-Bayes spread; the
    estimates' own robust spread (1.4826 x their median absolute deviation: no
    deconvolution, which is the population's spread plus the estimates' noise, an upper
    bound under independence); one material's spread
    (:data:`~jaxrefl.svbrdf._population.ALPHA_FLOOR_LOG_STD`); and |c - shared| / 1.645,
    since two estimates of the typical width that disagree say the photos do not pin it
    down, and the population holds both within its 90% range. (log ``shared``, the floor)
    where no pixel informs its width: the population is the shared width."""
    _c_eb, tau_eb = population(est, var)
    ok = np.isfinite(est) & np.isfinite(var) & (var > 0)
    if not ok.any():
        return float(shared), float(ALPHA_FLOOR_LOG_STD)
    c = float(np.median(est[ok]))
    spread = 1.4826 * float(np.median(np.abs(est[ok] - c)))
    return c, float(max(tau_eb, spread, ALPHA_FLOOR_LOG_STD, abs(c - shared) / _Z95))


def group_centres(est: np.ndarray, var: np.ndarray, centre: float) -> np.ndarray:
    """(N,) each pixel's population centre of log alpha: the median estimate ``est`` of the
    informing pixels in its group by ``var``'s quantiles (:data:`GROUPS` groups of at least
    :data:`_GROUP_PIXELS`; module docstring); ``centre`` where ``var`` is inf (no estimate)
    or too few pixels inform a group."""
    ok = np.isfinite(est) & np.isfinite(var) & (var > 0)
    out = np.full(est.shape, float(centre))
    g = min(GROUPS, int(np.sum(ok)) // _GROUP_PIXELS)
    if g < 2:
        return out
    edges = np.quantile(np.log(var[ok]), np.linspace(0.0, 1.0, g + 1)[1:-1])
    grp = np.searchsorted(edges, np.log(np.where(ok, var, 1.0)), side="right")
    for k in range(g):
        sel = ok & (grp == k)
        out[sel] = float(np.median(est[sel]))
    return out


def pixel_widths(
    cf,
    lp,
    data,
    theta: np.ndarray,
    capture,
    out_dir: str | Path | None = None,
    progress: bool = False,
    distributed=None,
) -> WidthSpread | None:
    """Each pixel's width and the move and variance it gives the map's parameters (module
    docstring) for a ``pooled`` capture fit ``cf`` (None for the other models).

    lp:      the map's log-posterior (its residual and space: the pooled fit's)
    data:    (N pixels) the map's data
    theta:   (N, P) the fit's optimum in ``lp``'s space (NaN: no estimate)
    capture: the capture as its files state the light (the per-pixel fit uses ``cf``'s)
    out_dir: where the per-pixel fit's tiles are written and read back (resume); None: in
             memory. ``progress``, ``distributed``: as :func:`fit_capture`'s
    """
    space = lp.space
    if "alpha" not in space.fixed or "alpha" in space.labels:
        return None
    alpha = float(np.asarray(space.fixed["alpha"]).reshape(-1)[0])
    n = theta.shape[0]
    # the per-pixel model under the light the pooled fit used, its other settings the same
    lit = capture if cf.light is None else cf.light.apply(capture)
    job = replace(cf.job, model=PER_PIXEL, light="fixed")
    own = fit_capture(lit, job, out_dir, progress=progress, distributed=distributed)
    a_hat = np.asarray(own.maps["alpha"], np.float64).reshape(-1)
    a_sd = np.asarray(own.maps["alpha_std"], np.float64).reshape(-1)
    own_space = own.model()[1]
    j = own_space.index("alpha")
    lo, hi = float(own_space.lower[j][0]), float(own_space.upper[j][0])  # j: a slice
    inside = (a_hat > lo * (1 + _AT_BOUND)) & (a_hat < hi * (1 - _AT_BOUND))
    with np.errstate(divide="ignore", invalid="ignore"):
        v_i = np.where(inside & np.isfinite(a_sd) & (a_sd > 0), (a_sd / a_hat) ** 2, np.inf)
    est = np.log(np.where(a_hat > 0, a_hat, np.nan))
    c, tau = population_bounds(est, v_i, np.log(alpha))
    c_i = group_centres(est, v_i, c)
    prec = np.where(np.isfinite(v_i), 1.0 / v_i, 0.0) + tau**-2
    m = (np.where(np.isfinite(v_i), est / v_i, 0.0) + c_i / tau**2) / prec
    w = np.where(np.isfinite(v_i), (1.0 / v_i) / prec, 0.0)
    a_std = np.asarray(cf.maps.get("alpha_std", np.full(n, np.nan)), np.float64).reshape(-1)
    shared = a_std / alpha
    log_std_shared = float(np.nanmedian(shared)) if np.isfinite(shared).any() else 0.0
    log_var = 1.0 / prec + log_std_shared**2
    sd = np.sqrt(log_var)
    a_lo, a_hi = ALPHA_RANGE
    mean = np.exp(m + 0.5 * log_var)
    std = mean * np.sqrt(np.expm1(log_var))
    q05 = np.clip(np.exp(m - _Z95 * sd), a_lo, a_hi)
    q95 = np.clip(np.exp(m + _Z95 * sd), a_lo, a_hi)
    # the other parameters: towards the per-pixel fit's by the shrinkage weight, and the
    # width's spread through the slopes of the pooled pixels' conditional optima
    ok = np.all(np.isfinite(theta), -1)
    t = np.where(ok[:, None], theta, 0.0)
    x_pool = np.asarray(space.natural_vector(jnp.asarray(t)), np.float64)
    own_theta = np.asarray(own.theta, np.float64)
    own_ok = np.all(np.isfinite(own_theta), -1)
    x_own = np.array(
        own_space.natural_vector(jnp.asarray(np.where(own_ok[:, None], own_theta, 0.0))),
        np.float64,
    )
    x_own[~own_ok] = np.nan
    labels = list(own_space.labels)
    x_own = x_own[:, [labels.index(lab) for lab in space.labels]]
    move = w[:, None] * (x_own - x_pool)
    v = np.full(theta.shape, np.nan)
    for a in range(0, n, _TILE):
        b = min(a + _TILE, n)
        blk = jax.tree.map(lambda x, a=a, b=b: x[a:b], data)
        v[a:b] = np.asarray(_slopes(lp.residual, jnp.asarray(t[a:b]), blk))
    slope = np.asarray(space.dnatural(jnp.asarray(t)), np.float64)
    var = (np.where(np.isfinite(v), v, 0.0) * slope) ** 2 / prec[:, None]
    down, up = np.full(theta.shape, np.nan), np.full(theta.shape, np.nan)
    cols = _lobe_columns(space, data.obs.shape[-1])
    if cols is not None:
        # albedo and F0 along the conditional optimum (module docstring)
        fill = np.where(np.isfinite(m), 1.0, 0.0)
        med = np.where(fill > 0, np.exp(np.where(fill > 0, m, 0.0)), alpha)
        lo_w, hi_w = np.where(fill > 0, q05, alpha), np.where(fill > 0, q95, alpha)
        x_sh, x_md = _curve(cf, data, (np.full(n, alpha), med), prior=True)
        ends = np.stack([x_md, *_curve(cf, data, (lo_w, med, hi_w), prior=False)])
        move[:, cols] = x_md - x_sh
        down[:, cols] = x_md - np.min(ends, 0)
        up[:, cols] = np.max(ends, 0) - x_md
        var[:, cols] = ((np.max(ends, 0) - np.min(ends, 0)) / (2 * _Z95)) ** 2
    bad = ~ok
    for arr in (mean, std, q05, q95):
        arr[bad] = np.nan
    move[bad | ~np.all(np.isfinite(move), -1)] = 0.0
    for arr in (var, down, up):
        arr[bad] = np.nan
    informing = int(np.sum(np.isfinite(v_i)))
    return WidthSpread(
        alpha,
        float(np.exp(c)),
        tau,
        log_std_shared,
        informing,
        mean,
        std,
        q05,
        q95,
        move,
        var,
        down,
        up,
    )


def _lobe_columns(space, channels: int) -> np.ndarray | None:
    """Columns of ``space``'s natural vector holding albedo then F0, in the order
    :func:`_conditional` returns them (None where the space holds them otherwise)."""
    labels = list(space.labels)
    want = [f"{p}.{ch}" for p in ("albedo", "specular") for ch in "RGB"[:channels]]
    if channels == 1:
        want = ["albedo", "specular"]
    if not all(w in labels for w in want):
        return None
    return np.array([labels.index(w) for w in want])


def relax_shared_width(umap, spread: WidthSpread, lower, upper):
    """The map with each pixel's parameters moved and widened by its own width (module
    docstring), inside the box [``lower``, ``upper``] (natural units) of its first P
    parameters, and the pixel's width appended as the last column ``alpha``."""
    p = spread.move.shape[1]
    move = np.where(np.isfinite(spread.move), spread.move, 0.0)
    extra = np.where(np.isfinite(spread.var), spread.var, 0.0)
    mean = np.array(umap.mean, np.float64)
    std = np.array(umap.std, np.float64)
    q05, q95 = np.array(umap.q05, np.float64), np.array(umap.q95, np.float64)
    lo, hi = np.asarray(lower, np.float64)[:p], np.asarray(upper, np.float64)[:p]
    m0 = mean[:, :p]
    m1 = np.clip(m0 + move, lo, hi)
    s0 = std[:, :p]
    # A normal wider than the box says less than the box does: the widened spread stops at
    # that of the uniform distribution over it (never below the map's own spread).
    s1 = np.maximum(s0, np.minimum(np.sqrt(s0**2 + extra), (hi - lo) / np.sqrt(12.0)))
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(s0 > 0, s1 / s0, 1.0)
    n05 = np.clip(m1 - (m0 - q05[:, :p]) * factor, lo, hi)
    n95 = np.clip(m1 + (q95[:, :p] - m0) * factor, lo, hi)
    # where the width's share of each end is known (albedo, F0): the two in quadrature
    down, up = spread.down, spread.up
    exact = np.isfinite(down) & np.isfinite(up) & (s0 > 0)
    with np.errstate(invalid="ignore"):
        e05 = m1 - np.sqrt((m0 - q05[:, :p]) ** 2 + np.where(exact, down, 0.0) ** 2)
        e95 = m1 + np.sqrt((q95[:, :p] - m0) ** 2 + np.where(exact, up, 0.0) ** 2)
    q05[:, :p] = np.where(exact, np.clip(e05, lo, hi), n05)
    q95[:, :p] = np.where(exact, np.clip(e95, lo, hi), n95)
    # A pixel whose posterior had no spread (a std of 0) gets the width's share alone.
    flat = s0 <= 0
    q05[:, :p] = np.where(flat, np.clip(m1 - _Z95 * s1, lo, hi), q05[:, :p])
    q95[:, :p] = np.where(flat, np.clip(m1 + _Z95 * s1, lo, hi), q95[:, :p])
    mean[:, :p], std[:, :p] = m1, s1

    def col(a, b):
        return np.concatenate([a, np.asarray(b, np.float64)[:, None]], axis=1)

    lap = np.array(umap.laplace_std, np.float64)
    return replace(
        umap,
        labels=(*umap.labels, "alpha"),
        mean=col(mean, spread.mean),
        std=col(std, spread.std),
        q05=col(q05, spread.q05),
        q95=col(q95, spread.q95),
        laplace_std=col(lap, spread.std),
    )
