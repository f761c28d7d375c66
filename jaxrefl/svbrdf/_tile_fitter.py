"""One tile of a capture fitted: the fit, its Laplace step and each photo's squared errors.

:class:`TileFitter` turns a tile's :class:`~jaxrefl.fit.PixelData` into the arrays a tile file
holds (:data:`jaxrefl.svbrdf._tile_store.TILE_KEYS`); it is a pure function of the tile's data,
so every tile of a job runs the same compiled programs. It also serves the model selection
(:meth:`TileFitter.score`: held-out errors without the Laplace step) and the score test of a
two-stage model's slopes (:meth:`TileFitter.tilt_evidence`).

Two-stage models (:data:`jaxrefl.svbrdf._models.TWO_STAGE`, ``ggx_normal``): the flat model
is fitted first, then the tilted model's MAP fit starts from the flat optimum with the slopes
at each of :data:`TILT_STARTS`; per pixel the fit of lower cost is kept.

The fitter sets some of the job's solver settings itself (the noise scale of ``pooled``, the
model's loss, the lean LM's compaction and fused rounds, the tilted stage's iterations):
:meth:`TileFitter.settings` says what runs, and the resume manifest records it.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import fit
from jaxrefl._errors import JaxreflError

from ._data import pixel_block, resolvable_alpha
from ._job_types import FitJob
from ._models import TWO_STAGE, capture_model
from ._pooled import PoolChoice, choose_pooled
from ._score_test import score_test
from ._width_laplace import width_terms as shared_width_terms

__all__ = ["STAGES", "TILT_STARTS", "TileFitter", "extend_start", "traced_noise"]

# The stages of a tile, in order (the report's ``timings.stages_s``).
STAGES = ("read", "fit", "laplace", "errors", "write")
# Starting slopes besides 0: four at this radius (11 degrees) along the axes. From the flat
# start alone some tilted pixels stay in another minimum, where colour and width explain the
# highlight's shift; the ring reaches the tilt's basin (tests/test_svbrdf.py checks recovery).
TILT_RING = 0.2
TILT_STARTS = (
    np.zeros(2),
    *(TILT_RING * np.array(v, float) for v in ((1, 0), (0, 1), (-1, 0), (0, -1))),
)
# The second stage starts from a flat optimum that is often at a bound (F0 at the dielectric
# cap, alpha at its floor), where the sigmoid has no slope, and moves slowly at first: its LM
# gets this many iterations at least.
STAGE2_ITERS = 150


class TileFitter:
    """Fit one tile: fit, Laplace, held-out error; pure function of the tile's data."""

    def __init__(
        self,
        capture,
        job: FitJob,
        pooled: PoolChoice | None = None,
        *,
        width_terms: bool = True,
    ):
        """``pooled``: ``pooled``'s choice when already made for these training photos.
        The lean LM gathers its slow pixels into compaction stages as ``job.compact`` says
        (None: by the capture's size, :meth:`FitJob.compacts`).
        ``width_terms``: for ``pooled``, each pixel's share of the shared width's Laplace
        uncertainty (:mod:`jaxrefl.svbrdf._width_laplace`; model selection needs no covariance)."""
        self.capture = capture
        self.width_terms = width_terms
        self.job = job
        self.compact = job.compacts(capture.shape[1] * capture.shape[2])
        k = capture.n_photos
        bad = [i for i in job.holdout if not 0 <= i < k]
        if bad:
            raise JaxreflError(f"--holdout photo(s) {bad} out of range: the capture has {k} photos")
        if len(job.holdout) >= k:
            raise JaxreflError("every photo is held out: nothing left to fit")
        self.train = np.ones(k, bool)
        self.train[list(job.holdout)] = False
        # The resolvable width of the training photos: held-out ones resolve nothing.
        self.alpha_min = (
            resolvable_alpha(capture, photos=self.train) if job.alpha_min is None else job.alpha_min
        )
        self.pooled: PoolChoice | None = None
        if job.model == "pooled":
            self.pooled = pooled or choose_pooled(
                capture, self.train, self.alpha_min, dtype=job.dtype
            )
        self.model, self.space = capture_model(
            job.model,
            channels=capture.shape[-1],
            alpha_min=self.alpha_min,
            alpha=None if self.pooled is None else self.pooled.alpha,
        )
        self.noise: fit.NoiseModel = traced_noise(job.config.noise, job.dtype)
        self.prior = None
        self.known_noise = None  # noise variance the Laplace step takes as known
        if self.pooled is not None and self.pooled.alpha is not None:
            # The F0 prior is in noise units: the noise scale is the selection's estimate
            # unless the job gives one (a prior's scale is tied to the noise scale).
            if self.noise.scale_unknown:
                # An array, not a float: equinox's jit would treat a float as static and
                # compile again for every capture or leave-one-out fold.
                assert self.pooled.sigma is not None  # choose_pooled sets it with alpha
                sigma = jnp.asarray(self.pooled.sigma, job.dtype)
                self.noise = self.noise.with_scale(sigma)
                self.known_noise = float(self.pooled.sigma) ** 2
            chans = [
                lab.split(".", 1)[1] for lab in self.space.labels if lab.startswith("specular.")
            ]
            self.prior = fit.gaussian_prior(
                self.space,
                {
                    f"specular.{ch}": (mu, sd)
                    for ch, mu, sd in zip(
                        chans, self.pooled.prior_mean, self.pooled.prior_std, strict=True
                    )
                },
            )
        assert job.config.loss is not None  # FitJob gives a named (not auto) model its loss
        self.loss: fit.Loss = job.config.loss
        self.residual = fit.make_residual(self.model, self.space, self.noise, self.loss, self.prior)
        self.config = job.config.replace(noise=self.noise, loss=self.loss)
        if not self.compact and isinstance(self.config.solver, fit.LMOptions):
            self.config = self.config.replace(solver=replace(self.config.solver, compact_stages=()))
        if job.model == "pooled" and isinstance(self.config.solver, fit.LMOptions):
            # Linear in its free parameters (alpha is shared) and started at the exact
            # optimum (initial_theta), the pooled model's LM mostly confirms: its steps are
            # cheap and its rounds many, which fused rounds serve better (LMOptions).
            self.config = self.config.replace(solver=replace(self.config.solver, host_fused=True))
        self.dtype = job.dtype
        # Seconds per stage of the tiles fitted so far (the report's ``stages_s``).
        self.stage_s: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self.first = None  # (model, space) of the first stage of a two-stage model
        if job.model in TWO_STAGE:
            self.first = capture_model(
                TWO_STAGE[job.model], channels=capture.shape[-1], alpha_min=self.alpha_min
            )

    @property
    def tilted_solver(self) -> fit.Solver:
        """The solver of a two-stage model's tilted fit: the job's, with at least
        :data:`STAGE2_ITERS` iterations. In one plain loop every pixel of a block would take
        the slowest pixel's steps, so it keeps the job's compaction stages whatever the size
        of the job."""
        solver = self.job.config.solver
        return replace(solver, max_iters=max(solver.max_iters, STAGE2_ITERS))

    def settings(self) -> dict[str, Any]:
        """The fit configuration that runs, as JSON (:meth:`jaxrefl.fit.FitConfig.to_json`):
        the job's with what the fitter sets (module docstring); for a two-stage model also
        the tilted fit's solver (its noise scale is each tile's own estimate)."""
        out: dict[str, Any] = {"config": self.config.to_json(), "compact": self.compact}
        if self.first is not None:
            out["tilted_solver"] = self.tilted_solver.to_json()
        return out

    @property
    def estimates_noise(self) -> bool:
        """Whether the Laplace step estimates each pixel's noise scale from its residuals
        (False where the variance is known: ``pooled``'s capture-wide scale, or the
        two-stage model's first-stage median under Gaussian noise of unknown scale)."""
        if self.known_noise is not None:
            return False
        return not (self.first is not None and self.noise.scale_unknown)

    def data(self, start: int, stop: int):
        return pixel_block(self.capture, start, stop, self.job.tile_pixels, dtype=self.job.dtype)

    def _two_stage(self, fit_data):
        """The flat model's fit, then the tilted model's MAP fit from the flat optimum with
        each slope of ``TILT_STARTS`` (per pixel the lowest cost wins).

        The prior tilt ~ N(0, tilt_std^2) needs residuals in units of the noise: with an
        unknown sigma it is the median over the tile's pixels of the flat fit's estimated
        noise scale (empirical Bayes). Returns (fit result, residual, noise variance or None
        where the Laplace step should estimate it)."""
        assert self.first is not None  # called for two-stage models only
        model1, space1 = self.first
        r1 = fit.fit_pixels(model1, fit_data, config=self.config, space=space1)
        noise, sigma, _ = self._tilt_noise(r1, fit_data)
        prior = self._tilt_prior()
        config2 = self.config.replace(noise=noise, solver=self.tilted_solver)
        best = None
        for tilt in TILT_STARTS:
            init = extend_start(r1, self.space, fit_data.obs.dtype, tilt)
            r = fit.fit_pixels(
                self.model, fit_data, config=config2, space=self.space, init=init, prior=prior
            )
            best = r if best is None else _keep_lower(best, r)
        res = fit.make_residual(self.model, self.space, noise, self.loss, prior)
        return best, res, None if sigma is None else sigma * sigma

    def _tilt_noise(self, r1, fit_data):
        """(noise model of the tilted fit, its sigma or None, each pixel's own noise variance
        (N,) or None) from the flat fit ``r1``. With Gaussian noise of unknown scale, sigma is
        the median over the pixels of the flat fit's estimated noise scale (empirical Bayes:
        the slopes' prior is in noise units); a known noise model is kept as it is."""
        noise = self.noise
        if not noise.scale_unknown:
            return noise, None, None
        assert self.first is not None  # called for two-stage models only
        model1, space1 = self.first
        res1 = fit.make_residual(model1, space1, noise, self.loss)
        s2_all = np.asarray(fit.laplace(r1, fit_data, residual=res1).noise_var)
        s2 = s2_all[np.isfinite(s2_all) & (s2_all > 0)]
        # No pixel with an estimate (all masked): any scale will do, nothing is fitted.
        sigma = float(np.sqrt(np.median(s2))) if s2.size else 1.0
        # An array, not a float: equinox's jit treats a float as static, and a new value in
        # every tile or fold would compile the tilted fit again.
        noise = noise.with_scale(jnp.asarray(sigma, fit_data.obs.dtype))
        return noise, sigma, s2_all

    def _tilt_prior(self) -> fit.GaussianPrior:
        """The slopes' zero-mean prior, std ``tilt_std`` (in the noise units of the fit)."""
        t = float(self.job.tilt_std)
        return fit.gaussian_prior(self.space, {"tilt_x": (0.0, t), "tilt_y": (0.0, t)})

    def tilt_evidence(self, r1, fit_data) -> np.ndarray:
        """Sums over the pixels of (T, E, V), the score test of the slopes at the flat fit
        ``r1`` of ``fit_data`` (:mod:`jaxrefl.svbrdf._score_test`): T / E near 1 says the
        photos show no tilt beyond noise. For two-stage models."""
        noise, sigma, s2 = self._tilt_noise(r1, fit_data)
        res = fit.make_residual(self.model, self.space, noise, self.loss, self._tilt_prior())
        theta = extend_start(r1, self.space, fit_data.obs.dtype, np.zeros(2))
        n = theta.shape[0]
        if s2 is None:
            scale = np.ones(n)
        else:
            # Each pixel in units of its own noise (c of the score test). Its estimate is
            # floored at 1% of the median scale: a pixel fitted to rounding error would
            # otherwise weigh without limit.
            s2 = np.where(np.isfinite(s2), s2, sigma * sigma)
            scale = sigma * sigma / np.maximum(s2, 1e-4 * sigma * sigma)
        extra = tuple(self.space.index(nm).start for nm in ("tilt_x", "tilt_y"))
        t, e, v = score_test(
            res, jnp.asarray(theta), fit_data, extra, jnp.asarray(scale, theta.dtype)
        )
        return np.array([float(jnp.sum(t)), float(jnp.sum(e)), float(jnp.sum(v))])

    def _fit(self, data, train=None):
        """(fit result, residual, known noise variance or None, fitted data) of the pixels of
        ``data`` on the job's training photos, or per pixel on ``train`` ((N, K) bool)."""
        if train is None:
            train_w = jnp.asarray(self.train, data.weight.dtype)[None, :, None]
        else:
            train_w = jnp.asarray(train, data.weight.dtype)[:, :, None]
        fit_data = eqx.tree_at(lambda d: d.weight, data, data.weight * train_w)
        res, noise_var = self.residual, self.known_noise
        if self.first is None:
            r = fit.fit_pixels(
                self.model, fit_data, config=self.config, space=self.space, prior=self.prior
            )
        else:
            r, res, noise_var = self._two_stage(fit_data)
        return r, res, noise_var, fit_data

    def score(self, data, train):
        """Squared errors and counts (N, K) of the fit of ``data`` per pixel on ``train``
        ((N, K) bool), for every photo: the held-out scores of a selection, without the
        Laplace step the maps need. Returns (errors, counts, fit result, fitted data)."""
        t0 = time.perf_counter()
        r, res, _, fit_data = self._fit(data, train)
        sse, cnt = _errors(res, r.theta, data)
        out = np.asarray(sse), np.asarray(cnt)
        self.stage_s["fit"] += time.perf_counter() - t0
        return (*out, r, fit_data)

    def __call__(self, data, n: int, train=None) -> dict[str, np.ndarray]:
        """Fit the first ``n`` pixels of ``data`` on the job's training photos, or per pixel
        on ``train`` ((N, K) bool: several held-out folds stacked in one tile)."""
        t0 = time.perf_counter()
        r, res, noise_var, fit_data = self._fit(data, train)
        jax.block_until_ready((r.theta, r.status))
        t1 = time.perf_counter()
        # A prior's scale is tied to the noise scale: that one is then known, not re-estimated.
        known: Literal["known", "estimate"] = "known" if noise_var is not None else "estimate"
        lap = fit.laplace(r, fit_data, residual=res, options=fit.LaplaceOptions(noise=known))
        lap_noise = lap.noise_var if noise_var is None else jnp.full_like(lap.noise_var, noise_var)
        jax.block_until_ready((lap.std, lap_noise))
        n_rows, p = r.theta.shape
        width_v, width_s = np.zeros((n_rows, p)), np.zeros(n_rows)
        if self.width_terms and self.pooled is not None and self.pooled.alpha is not None:
            width_v, width_s = shared_width_terms(res, r.theta, fit_data, lap.std)
        t2 = time.perf_counter()
        sse, cnt = _errors(res, r.theta, data)
        out = {
            "theta": r.theta,
            "status": r.status,
            "cost": r.cost,
            "iterations": r.iterations,
            "n_used": r.n_used,
            "std": lap.std,
            "corr": lap.corr,
            "noise_var": lap_noise,
            "flag": lap.flag,
            "sse": sse,
            "cnt": cnt,
            "width_v": width_v,
            "width_s": width_s,
        }
        out = {k: np.asarray(v)[:n] for k, v in out.items()}
        t3 = time.perf_counter()
        self.stage_s["fit"] += t1 - t0
        self.stage_s["laplace"] += t2 - t1
        self.stage_s["errors"] += t3 - t2
        return out


def extend_start(r1, space, dtype, tilt) -> np.ndarray:
    """Theta (N, P) of ``space`` from a first-stage fit ``r1``: its natural values, with the
    slopes at ``tilt`` ((2,)), bounded entries moved off their bounds (``off_bounds``);
    pixels without a first-stage estimate start at the defaults throughout."""
    nat = dict(r1.params)
    nat["tilt_x"] = np.full(r1.cost.shape, tilt[0])
    nat["tilt_y"] = np.full(r1.cost.shape, tilt[1])
    theta = np.array(space.from_natural(nat, dtype=dtype))
    bad = ~np.all(np.isfinite(theta), axis=-1)
    theta[bad] = np.asarray(space.default_theta(dtype))
    theta = np.array(space.off_bounds(theta))
    return theta


# The fields of a fit result that go with each pixel's candidate (beside its cost).
_PER_PIXEL = ("params", "theta", "status", "iterations", "n_used")


def traced_noise(noise: fit.NoiseModel, dtype) -> fit.NoiseModel:
    """``noise`` with a capture's estimated shape (:class:`~jaxrefl.fit.LevelNoise`) as
    arrays: equinox's jit treats a float as static and would compile the tile program again
    for every capture's value."""
    if isinstance(noise, fit.LevelNoise) and noise.scale is None:
        gain, rel = jnp.asarray(noise.gain, dtype), jnp.asarray(noise.rel, dtype)
        return fit.LevelNoise(gain=gain, rel=rel)
    return noise


def _keep_lower(a, b):
    """Per pixel, the fit result of lower cost (:func:`jaxrefl.fit.keep_lower`: a NaN cost
    never wins)."""
    la, lb = a.linearisation, b.linearisation
    # The curvature goes with the theta it was taken at; without both there is none.
    same = la is not None and lb is not None and fit.same_residual(la.residual, lb.residual)

    def candidate(r):
        out = {f: getattr(r, f) for f in _PER_PIXEL}
        if same:
            out["jtj"], out["active"] = r.linearisation.jtj, r.linearisation.active
        return out

    cost, kept = fit.keep_lower(a.cost, candidate(a), b.cost, candidate(b))
    lin = None
    if same:
        lin = replace(la, jtj=kept.pop("jtj"), active=kept.pop("active"))
    return replace(a, **kept, cost=cost, linearisation=lin)


@eqx.filter_jit
def _errors(res, theta, data):
    """Per pixel and photo: sum of squared radiance errors and count over the observations
    that are values (weight > 0, not censored); NaN theta (no estimate) counts nothing."""
    ok_t = jnp.all(jnp.isfinite(theta), axis=-1)
    t = jnp.where(ok_t[:, None], theta, 0.0)
    pred = jax.vmap(res.predict)(t, data)
    use = (data.weight > 0) & (data.censored == 0) & ok_t[:, None, None]
    err = jnp.where(use, pred - data.obs, 0.0)
    return jnp.sum(err * err, axis=-1), jnp.sum(use, axis=-1)
