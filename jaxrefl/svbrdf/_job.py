"""The main job: a planar capture in, per-pixel reflectance maps with uncertainty out.

:func:`fit_capture` fits every pixel of a :class:`jaxrefl.io.Capture` independently
(:func:`jaxrefl.fit.fit_pixels`, lean batched LM by default), computes the Laplace
covariance of every pixel (:func:`jaxrefl.fit.laplace`) and, for held-out photos, the
prediction error. Pixels go through in tiles of ``tile_pixels`` (row-major, the last one
padded), so the working set is one tile whatever the image size; every tile has the same
shape and reuses one compiled program.

Interruption and resume: with an ``out_dir``, each finished tile is written to
``out_dir/tiles/tile_NNNNN.npz`` (temporary file + rename: a tile file is complete or
absent) beside a ``manifest.json`` naming the job and the capture. A rerun with the same
job and capture loads the tiles already there and computes only the missing ones (none is
lost, none recomputed); a different job or capture in the same folder is refused with a
message, and a corrupt tile file is recomputed.

Several processes and hosts (``distributed``, a :class:`jaxrefl.fit.Distributed`): the
same job runs in every process on a shared ``out_dir``. Process 0 checks and prepares the
folder while the others wait; every process lists the missing tiles, then fits every n-th
of them from its id on (n processes) and writes them as above; after a barrier every
process reads the others' tiles and assembles the maps. Each tile is fitted by one process
with the one compiled tile program, so the maps equal a one-process run's bit for bit; a
process that dies leaves its finished tiles for a rerun (with any number of processes).
The report's ``timings.processes`` gives each process's tiles and seconds; ``run_s`` is
then the slowest process's.

Timings: ``compile_s`` is measured by a warm-up call on the first tile's data (time of that
call minus the time of the same tile in the run), ``run_s`` is the sum of the tiles' times
(from waiting for its data to writing its file). A tile's data is read on a second thread
while the tile before it is fitted.
``stages_s`` splits the tiles' time (warm-up excluded) into ``read`` (the wait for the
tile's :class:`~jaxrefl.fit.PixelData` from the photos), ``fit`` (:func:`~jaxrefl.fit.fit_pixels`:
start and solver), ``laplace``, ``errors`` (per-photo errors and the copy of the tile's
results to the host) and ``write`` (the tile file); each stage waits for its results, so
the split is exact up to the timer. ``choose_s`` is the time of ``auto``'s model choice.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import brdf, fit
from jaxrefl._errors import JaxreflError
from jaxrefl.fit import (
    Distributed,
    Status,
    process_barrier,
    process_gather,
    process_share,
    undefined_correlations,
)
from jaxrefl.io import corr_name, map_name, save_npz_atomic

from ._auto import ModelChoice, choose_model
from ._check import ModelCheck, bound_bits, check_counts, ppc_failed
from ._data import pixel_block, resolvable_alpha
from ._light import LIGHT_CHOICES, estimate_light
from ._models import ALPHA_RANGE, TWO_STAGE, capture_model
from ._pooled import PoolChoice, choose_pooled
from ._score_test import score_test
from ._shared import WidthUncertainty, widen
from ._shared import width_terms as shared_width_terms

__all__ = ["DEFAULT_LOSS", "CaptureFit", "FitJob", "fit_capture", "map_name"]

# The stages of a tile, in order (module docstring, ``stages_s``).
STAGES = ("read", "fit", "laplace", "errors", "write")
# Models whose default loss is not L2. Huber's threshold is one noise std (the pooled model
# estimates that std): a glint or a misregistered edge in one photo then pulls the shared
# lobe and the pixel's F0 linearly, not quadratically.
DEFAULT_LOSS: dict[str, fit.Loss] = {"pooled": fit.Huber()}
_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
# Captures of fewer pixels than this are fitted by the lean LM in one plain loop of steps
# rather than in compaction stages (fit.LMOptions.compact_stages; per-pixel results do not
# depend on it). Each stage is one more compiled copy of the LM step, several seconds of
# compile for a capture model; the steps compaction saves (it stops iterating the converged
# pixels of a block) only repay that over some tens of 4096-pixel tiles.
COMPACT_MIN_PIXELS = 1 << 17


@dataclass(frozen=True)
class FitJob:
    """What to fit and how (everything that changes the result; see :func:`fit_capture`).

    model:      a name of :data:`jaxrefl.svbrdf.CAPTURE_MODELS`, or ``auto`` (the default):
                the candidate that best predicts held-out training photos
                (:func:`jaxrefl.svbrdf.choose_model`; the report's ``auto`` says why)
    holdout:    photo indices left out of the fit and used to measure prediction error
    tile_pixels: pixels per tile (memory is constant in the image size, about 1 kB a pixel)
    config:     a :class:`jaxrefl.fit.FitConfig`:

                * ``solver``: :class:`~jaxrefl.fit.LMOptions` (default), or a library solver
                  (:class:`~jaxrefl.fit.OptimistixLM`, :class:`~jaxrefl.fit.JaxoptLM`),
                  with its iteration budget; captures of fewer than
                  :data:`COMPACT_MIN_PIXELS` pixels run the lean LM as one plain loop
                  (its ``compact_stages`` dropped; per-pixel results are the same), unless
                  :func:`fit_capture` is told otherwise (its ``compact``)
                * ``noise``: :class:`~jaxrefl.fit.GaussianNoise` (default: sigma unknown, the
                  Laplace step estimates its scale per pixel) or
                  :class:`~jaxrefl.fit.ShotNoise` (variance read^2 + gain * obs), in linear
                  radiance units; robust-loss thresholds are in these units
                * ``loss``: :class:`~jaxrefl.fit.L2`, :class:`~jaxrefl.fit.Huber` or
                  :class:`~jaxrefl.fit.Cauchy` (robust to highlights/outliers); None (the
                  default): the model's own, :data:`jaxrefl.svbrdf.DEFAULT_LOSS`
                  (:class:`~jaxrefl.fit.Huber` for ``pooled``, whose one lobe should not bend
                  to a glint or a misregistered edge in one photo; L2 otherwise); ``auto``
                  keeps None until it has chosen the model
                * ``dtype``: float32 (default; None means float32 here) or float64
    alpha_min:  lower bound of alpha; None: the capture's resolvable width
                (:func:`jaxrefl.svbrdf.resolvable_alpha`); 1e-3 lets lobes be as narrow
                as the models allow
    tilt_std:   ``ggx_normal`` only: std of the zero-mean Gaussian prior on the slopes
                ``tilt_x``, ``tilt_y`` (MAP fit; 0.1 is about 6 degrees). Without it the
                slopes of a real capture overfit: a tilt turns a highlight seen in one
                photo into a steep normal rather than a brighter lobe.
    light:      the flash as the capture states it (``fixed``, the default here), or
                estimated first (:func:`jaxrefl.svbrdf.estimate_light`): ``offset`` (its
                offset from the lens), ``offset+gains`` (and a gain per photo), ``auto``
                (whichever held-out observations support; ``jaxrefl fit``'s default); the
                report's ``light`` says what and why
    """

    model: str = "auto"
    holdout: tuple[int, ...] = ()
    tile_pixels: int = 4096
    config: fit.FitConfig = field(default_factory=fit.FitConfig)
    alpha_min: float | None = None
    tilt_std: float = 0.1
    light: str = "fixed"

    def __post_init__(self) -> None:
        if self.light not in LIGHT_CHOICES:
            raise JaxreflError(
                f"FitJob.light must be one of {', '.join(LIGHT_CHOICES)}, not {self.light!r}"
            )
        if self.model != "auto":
            capture_model(self.model)  # raises for an unknown name
        cfg = self.config
        if not isinstance(cfg, fit.FitConfig):
            raise TypeError(f"config must be a fit.FitConfig, not {type(cfg).__name__}")
        if cfg.dtype is None:
            cfg = cfg.replace(dtype=np.float32)
        if cfg.dtype not in _DTYPES:
            raise JaxreflError(f"dtype must be float32 or float64, not {cfg.dtype}")
        # ``auto`` leaves the loss to the model it chooses (None stays None until then).
        if cfg.loss is None and self.model != "auto":
            cfg = cfg.replace(loss=DEFAULT_LOSS.get(self.model, fit.L2()))
        object.__setattr__(self, "config", cfg)
        if self.tile_pixels < 1:
            raise JaxreflError(f"tile_pixels must be positive, got {self.tile_pixels}")
        if not self.tilt_std > 0:
            raise JaxreflError(f"tilt_std must be positive, got {self.tilt_std}")
        lo, hi = ALPHA_RANGE
        if self.alpha_min is not None and not lo <= self.alpha_min <= hi:
            raise JaxreflError(f"alpha_min must be in [{lo:g}, {hi:g}], got {self.alpha_min}")
        object.__setattr__(self, "holdout", tuple(sorted({int(i) for i in self.holdout})))

    @property
    def dtype(self) -> np.dtype:
        """The computation dtype (``config.dtype``, float32 or float64)."""
        return np.dtype(self.config.dtype)  # __post_init__ sets float32 or float64

    def to_json(self) -> dict[str, Any]:
        """The job as plain JSON values (the resume manifest's and report's ``job``); the
        fit configuration's objects as their ``to_json`` (``{"type": "shot", ...}``)."""
        return {
            "model": self.model,
            "holdout": list(self.holdout),
            "tile_pixels": self.tile_pixels,
            "config": self.config.to_json(),
            "alpha_min": self.alpha_min,
            "tilt_std": self.tilt_std,
            "light": self.light,
        }


@dataclass
class CaptureFit:
    """Result of :func:`fit_capture`: maps (H, W) by channel name, and a report.

    maps:    keyed by :func:`jaxrefl.io.map_name` (the names of ``maps.exr``'s channels, a
             scalar map without its ``.Y``; table in :mod:`jaxrefl.io._channels`):
             ``albedo.R/G/B``, ``specular``, ``alpha``, ``roughness`` (= sqrt(alpha)), their
             standard deviations (``albedo_std.R``, ``specular_std``, ``alpha_std``,
             ``roughness_std``), correlations ``corr_<a>_<b>``, ``status`` (fit
             :class:`jaxrefl.fit.Status`), ``laplace_flag`` (:class:`jaxrefl.fit.LaplaceFlag`
             bits), ``misspecified`` (:class:`jaxrefl.svbrdf.ModelCheck` bits: where the
             model cannot be right, :mod:`jaxrefl.svbrdf._check`), ``noise_std``
             (estimated), ``cost``, ``n_used``, ``iterations``
    report:  what ``report.json`` holds (timings, counts, held-out error, model)
    """

    maps: dict[str, np.ndarray]
    report: dict[str, Any]
    labels: tuple[str, ...]
    theta: np.ndarray  # (H*W, P)
    job: FitJob
    tiles_computed: int = 0
    tiles_loaded: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def model(self) -> tuple[brdf.BRDF, Any]:
        """(model, parameter space) the pixels were fitted with (for ``pooled``: the choice
        and shared alpha of ``extra["pooled"]``)."""
        pooled = self.extra.get("pooled")
        return capture_model(
            self.job.model,
            channels=self._channels,
            alpha_min=self.extra.get("alpha_min"),
            alpha=None if pooled is None else pooled.alpha,
        )

    def params(self) -> dict[str, np.ndarray]:
        """Natural parameters as (H, W, ...) arrays for ``model.eval``."""
        _model, space = self.model()
        h, w = self.maps["status"].shape
        t = jnp.asarray(np.nan_to_num(self.theta), dtype=self.job.dtype)
        nat = space.to_natural(t)
        return {k: np.asarray(v).reshape(h, w, *v.shape[1:]) for k, v in nat.items()}

    @property
    def _channels(self) -> int:
        return int(self.extra.get("channels", 3))


def _capture_fingerprint(capture) -> dict[str, Any]:
    k, h, w, c = capture.shape
    digest = hashlib.sha1()
    digest.update(
        np.ascontiguousarray(capture.images[:, :: max(1, h // 16), :: max(1, w // 16)]).tobytes()
    )
    digest.update(np.ascontiguousarray(capture.status).tobytes()[:1_000_000])
    return {
        "shape": [k, h, w, c],
        "source": None if capture.source is None else str(capture.source),
        "digest": digest.hexdigest(),
    }


_TILE_KEYS = (
    "theta",
    "status",
    "cost",
    "iterations",
    "n_used",
    "std",
    "corr",
    "noise_var",
    "flag",
    "sse",
    "cnt",
    "width_v",
    "width_s",
)


def _load_tile(path: Path, n: int) -> dict[str, np.ndarray] | None:
    """A saved tile of ``n`` pixels, or None where the file is truncated, corrupt, or holds
    another number of pixels or other arrays (then the tile is recomputed)."""
    try:
        with np.load(path) as z:
            tile = {k: z[k] for k in z.files}
    except Exception:  # truncated or corrupt: recompute it
        return None
    if any(k not in tile for k in _TILE_KEYS) or any(
        v.ndim == 0 or v.shape[0] != n for v in tile.values()
    ):
        return None
    return tile


class _TileFitter:
    """Fit one tile: fit, Laplace, held-out error; pure function of the tile's data."""

    def __init__(
        self,
        capture,
        job: FitJob,
        pooled: PoolChoice | None = None,
        *,
        compact: bool = True,
        width_terms: bool = True,
    ):
        """``pooled``: ``pooled``'s choice when already made for these training photos.
        ``compact``: the lean LM gathers its slow pixels into compaction stages (else one
        plain loop of steps; :func:`fit_capture` decides, see its ``compact``).
        ``width_terms``: for ``pooled``, each pixel's share of the shared width's Laplace
        uncertainty (:mod:`jaxrefl.svbrdf._shared`; model selection needs no covariance)."""
        self.capture = capture
        self.width_terms = width_terms
        self.job = job
        self.compact = compact
        k = capture.n_photos
        bad = [i for i in job.holdout if not 0 <= i < k]
        if bad:
            raise JaxreflError(f"--holdout photo(s) {bad} out of range: the capture has {k} photos")
        if len(job.holdout) >= k:
            raise JaxreflError("every photo is held out: nothing left to fit")
        self.train = np.ones(k, bool)
        self.train[list(job.holdout)] = False
        self.alpha_min = resolvable_alpha(capture) if job.alpha_min is None else job.alpha_min
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
        self.noise: fit.NoiseModel = job.config.noise
        self.prior = None
        self.known_noise = None  # noise variance the Laplace step takes as known
        if self.pooled is not None and self.pooled.alpha is not None:
            # The F0 prior is in noise units: the noise scale is the selection's estimate
            # unless the job gives one (a prior's scale is tied to the noise scale).
            if isinstance(self.noise, fit.GaussianNoise) and self.noise.sigma is None:
                # An array, not a float: equinox's jit would treat a float as static and
                # compile again for every capture or leave-one-out fold.
                assert self.pooled.sigma is not None  # choose_pooled sets it with alpha
                sigma = jnp.asarray(self.pooled.sigma, job.dtype)
                self.noise = fit.GaussianNoise(sigma=sigma)
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
        if not compact and isinstance(self.config.solver, fit.LMOptions):
            self.config = self.config.replace(solver=replace(self.config.solver, compact_stages=()))
        if job.model == "pooled" and isinstance(self.config.solver, fit.LMOptions):
            # Linear in its free parameters (alpha is shared) and started at the exact
            # optimum (initial_theta), the pooled model's LM mostly confirms: its steps are
            # cheap and its rounds many, which fused rounds serve better (LMOptions).
            self.config = self.config.replace(solver=replace(self.config.solver, host_fused=True))
        self.dtype = job.dtype
        # Seconds per stage of the tiles fitted so far (module docstring, ``stages_s``).
        self.stage_s: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self.first = None  # (model, space) of the first stage of a two-stage model
        if job.model in TWO_STAGE:
            self.first = capture_model(
                TWO_STAGE[job.model], channels=capture.shape[-1], alpha_min=self.alpha_min
            )

    @property
    def estimates_noise(self) -> bool:
        """Whether the Laplace step estimates each pixel's noise scale from its residuals
        (False where the variance is known: ``pooled``'s capture-wide scale, or the
        two-stage model's first-stage median under Gaussian noise of unknown scale)."""
        if self.known_noise is not None:
            return False
        two_stage_sigma = isinstance(self.noise, fit.GaussianNoise) and self.noise.sigma is None
        return not (self.first is not None and two_stage_sigma)

    def data(self, start: int, stop: int):
        return pixel_block(self.capture, start, stop, self.job.tile_pixels, dtype=self.job.dtype)

    def _two_stage(self, fit_data):
        """The flat model's fit, then the tilted model's MAP fit from the flat optimum with
        each slope of ``_TILT_STARTS`` (per pixel the lowest cost wins).

        The prior tilt ~ N(0, tilt_std^2) needs residuals in units of the noise: with an
        unknown sigma it is the median over the tile's pixels of the flat fit's estimated
        noise scale (empirical Bayes). Returns (fit result, residual, noise variance or None
        where the Laplace step should estimate it)."""
        assert self.first is not None  # called for two-stage models only
        model1, space1 = self.first
        r1 = fit.fit_pixels(model1, fit_data, config=self.config, space=space1)
        noise, sigma, _ = self._tilt_noise(r1, fit_data)
        prior = self._tilt_prior()
        # The tilted fit runs up to _STAGE2_ITERS steps: in one plain loop every pixel of a
        # block would take the slowest pixel's steps, so it keeps the job's solver (with its
        # compaction stages) whatever the size of the job.
        solver = self.job.config.solver
        config2 = self.config.replace(
            noise=noise, solver=replace(solver, max_iters=max(solver.max_iters, _STAGE2_ITERS))
        )
        best = None
        for tilt in _TILT_STARTS:
            init = _extend_start(r1, self.space, fit_data.obs.dtype, tilt)
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
        if not (isinstance(noise, fit.GaussianNoise) and noise.sigma is None):
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
        noise = fit.GaussianNoise(sigma=jnp.asarray(sigma, fit_data.obs.dtype))
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
        theta = _extend_start(r1, self.space, fit_data.obs.dtype, np.zeros(2))
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
        lap = fit.laplace(r, fit_data, residual=res, noise=known)
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


def _extend_start(r1, space, dtype, tilt) -> np.ndarray:
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


def _keep_lower(a, b):
    """Per pixel, the fit result of lower cost (a NaN cost never wins)."""
    ca, cb = np.asarray(a.cost), np.asarray(b.cost)
    take_b = np.isfinite(cb) & ~(ca <= cb)

    def pick(x, y):
        m = jnp.asarray(take_b).reshape(take_b.shape + (1,) * (jnp.ndim(x) - 1))
        return jnp.where(m, y, x)

    fields = ("params", "theta", "status", "cost", "iterations", "n_used")
    out = {f: jax.tree.map(pick, getattr(a, f), getattr(b, f)) for f in fields}
    la, lb = a.linearisation, b.linearisation
    # The curvature goes with the theta it was taken at; without both there is none.
    same = la is not None and lb is not None
    if same and fit.same_residual(la.residual, lb.residual):
        lin = replace(la, jtj=pick(la.jtj, lb.jtj), active=pick(la.active, lb.active))
    else:
        lin = None
    return replace(a, **out, linearisation=lin)


# Starting slopes besides 0: four at this radius (11 degrees) along the axes. From the flat
# start alone some tilted pixels stay in another minimum, where colour and width explain the
# highlight's shift; the ring reaches the tilt's basin (tests/test_svbrdf.py checks recovery).
_TILT_RING = 0.2
_TILT_STARTS = (
    np.zeros(2),
    *(_TILT_RING * np.array(v, float) for v in ((1, 0), (0, 1), (-1, 0), (0, -1))),
)
# The second stage starts from a flat optimum that is often at a bound (F0 at the dielectric
# cap, alpha at its floor), where the sigmoid has no slope, and moves slowly at first: its LM
# gets this many iterations at least.
_STAGE2_ITERS = 150


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


def _tiles(h: int, w: int, size: int) -> list[tuple[int, int]]:
    n = h * w
    return [(s, min(s + size, n)) for s in range(0, n, size)]


def _manifest(job: FitJob, capture, n_tiles: int) -> dict[str, Any]:
    from jaxrefl import __version__

    return {
        "job": job.to_json(),
        "capture": _capture_fingerprint(capture),
        "n_tiles": n_tiles,
        "jaxrefl": __version__,
    }


def _check_manifest(mpath: Path, manifest: dict[str, Any]) -> bool:
    """Whether ``mpath`` exists and names this job and capture (False: absent); raises where
    it is unreadable or names another fit (its tiles are not this fit's)."""
    if not mpath.exists():
        return False
    tiles = mpath.parent
    try:
        old = json.loads(mpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, OSError) as e:
        raise JaxreflError(
            f"{mpath}: unreadable resume manifest ({e}); the tiles beside it cannot be "
            "matched to this fit: use --restart (or another --out folder)"
        ) from None
    new = json.loads(json.dumps(manifest))  # as it reads back (tuples become lists)
    same = isinstance(old, dict) and all(old.get(k) == new[k] for k in ("job", "capture"))
    if not same:
        raise JaxreflError(
            f"{mpath}: the tiles in {tiles} belong to a different fit (another model, "
            "holdout, tile size, fit configuration or capture); use another --out "
            "folder or --restart"
        )
    return True


def _prepare_dir(out_dir: Path, manifest: dict[str, Any], restart: bool) -> Path:
    tiles = out_dir / "tiles"
    tiles.mkdir(parents=True, exist_ok=True)
    mpath = tiles / "manifest.json"
    if not restart and _check_manifest(mpath, manifest):
        return tiles
    for old_tile in tiles.glob("tile_*.npz"):
        old_tile.unlink()
    tmp = mpath.with_suffix(".tmp")
    tmp.write_text(json.dumps(manifest, indent=2))
    os.replace(tmp, mpath)
    return tiles


def _shared_dir(out_dir: Path, manifest: dict[str, Any], restart: bool) -> Path:
    """:func:`_prepare_dir` in a job of one or more processes: every process checks the
    manifest (the same files give every process the same error), process 0 alone creates
    the folder, writes the manifest or clears old tiles, and the others wait for it."""
    if jax.process_count() == 1:
        return _prepare_dir(out_dir, manifest, restart)
    if not restart:
        _check_manifest(out_dir / "tiles" / "manifest.json", manifest)
    if jax.process_index() == 0:
        _prepare_dir(out_dir, manifest, restart)
    process_barrier("jaxrefl fit: folder prepared")
    return out_dir / "tiles"


def fit_capture(
    capture,
    job: FitJob | None = None,
    out_dir: str | Path | None = None,
    *,
    restart: bool = False,
    progress: bool = False,
    on_tile: Callable[[int, int], None] | None = None,
    distributed: Distributed | None = None,
    compact: bool | None = None,
) -> CaptureFit:
    """Fit every pixel of ``capture`` (module docstring); returns the maps and a report.

    out_dir:  where tiles go (resume); None keeps everything in memory
    restart:  discard the tiles of an earlier run in ``out_dir``
    progress: show a tqdm progress bar over tiles
    on_tile:  called as ``on_tile(index, n_tiles)`` after each tile is saved (for tests
              and front ends; an exception raised there interrupts the run like Ctrl-C)
    distributed: run as one process of a group (:class:`jaxrefl.fit.Distributed`; every
              process calls ``fit_capture`` with the same capture, job and ``out_dir``, a
              folder they all see). Process 0 prepares ``out_dir``; the tiles missing
              there are split round-robin by process id, each written by its process
              alone; once all are in, every process returns the whole fit (process 0
              writes the outputs: :func:`write_outputs`). A process that dies leaves its
              finished tiles, which a rerun loads. Call ``distributed.initialize()``
              before loading the capture (:func:`jaxrefl.io.load_capture` computes with
              JAX, which fixes the process's devices); here it is a no-op then.
    compact:  whether the lean LM gathers its slow pixels into compaction stages, in the
              fit and in the model selection (per-pixel results do not depend on it; it
              trades compiled copies of the step for the steps it saves). None: where the
              capture has :data:`COMPACT_MIN_PIXELS` pixels or more. A caller that fits the
              same capture many times (:func:`jaxrefl.svbrdf.leave_one_out`) passes its
              own count of the work.
    """
    job = FitJob() if job is None else job
    if distributed is not None:
        if out_dir is None:
            raise JaxreflError(
                "a distributed fit needs out_dir: a folder every process can read and write "
                "(the processes exchange their tiles there)"
            )
        distributed.initialize()
    if out_dir is None and jax.process_count() > 1:
        raise JaxreflError(
            "fit_capture in a job of several processes needs out_dir: a folder every process "
            "can read and write (the processes exchange their tiles there)"
        )
    _k, h, w, c = capture.shape
    if compact is None:
        compact = h * w >= COMPACT_MIN_PIXELS
    # The light first (the capture as the estimate places it): every model sees the same.
    t_light = time.perf_counter()
    light = estimate_light(capture, job.light, job.holdout)
    capture = light.apply(capture)
    light_s = time.perf_counter() - t_light
    choice: ModelChoice | None = None
    t_choose = time.perf_counter()
    if job.model == "auto":
        choice = choose_model(capture, job, compact=compact)
        job = replace(job, model=choice.model)
    choose_s = time.perf_counter() - t_choose
    fitter = _TileFitter(
        capture, job, pooled=None if choice is None else choice.pooled, compact=compact
    )
    tiles = _tiles(h, w, job.tile_pixels)
    tdir = None
    if out_dir is not None:
        tdir = _shared_dir(Path(out_dir), _manifest(job, capture, len(tiles)), restart)

    results: list[dict[str, np.ndarray] | None] = [None] * len(tiles)
    loaded = 0
    if tdir is not None:
        for i in range(len(tiles)):
            p = tdir / f"tile_{i:05d}.npz"
            if p.exists():
                s_i, e_i = tiles[i]
                results[i] = _load_tile(p, e_i - s_i)
                loaded += results[i] is not None
    missing = [i for i, r in enumerate(results) if r is None]
    # Every process has listed the same missing tiles before any writes a new one.
    process_barrier("jaxrefl fit: tiles listed")
    todo = process_share(missing)

    compile_s = 0.0
    times: list[float] = []
    if todo:
        s0, e0 = tiles[todo[0]]
        t0 = time.perf_counter()
        jax.block_until_ready(fitter(fitter.data(s0, e0), e0 - s0))
        warm = time.perf_counter() - t0
        fitter.stage_s = dict.fromkeys(STAGES, 0.0)  # the warm-up call is not a tile
    iterator: Any = todo
    if progress and todo and jax.process_index() == 0:
        from tqdm.auto import tqdm

        iterator = tqdm(todo, desc="fit tiles", unit="tile")

    def read(j: int):
        return fitter.data(*tiles[todo[j]])

    # The next tile's data is read on a second thread while this one is fitted (reading is
    # NumPy work on the host, the fit XLA's); ``read`` counts only the wait for it.
    with ThreadPoolExecutor(max_workers=1) as pool:
        ahead = pool.submit(read, 0) if todo else None
        for j, i in enumerate(iterator):
            s, e = tiles[i]
            t0 = time.perf_counter()
            assert ahead is not None
            data = ahead.result()
            ahead = pool.submit(read, j + 1) if j + 1 < len(todo) else None
            fitter.stage_s["read"] += time.perf_counter() - t0
            out = fitter(data, e - s)
            t1 = time.perf_counter()
            if tdir is not None:
                save_npz_atomic(tdir / f"tile_{i:05d}.npz", **out)
            t2 = time.perf_counter()
            fitter.stage_s["write"] += t2 - t1
            times.append(t2 - t0)
            results[i] = out
            if on_tile is not None:
                on_tile(i, len(tiles))
    if todo:
        compile_s = max(0.0, warm - times[0])
    per_process = None
    if jax.process_count() > 1:
        per_process = _collect(tdir, tiles, results, len(todo), compile_s, float(np.sum(times)))

    done = [r for r in results if r is not None]
    cat = {key: np.concatenate([r[key] for r in done]) for key in done[0]}
    width = None
    if fitter.width_terms and fitter.pooled is not None and fitter.pooled.alpha is not None:
        # The shared width's share of every pixel's Laplace covariance (_shared). A
        # correlation undefined for a zero std enters as 0 (the covariance entry it stands
        # for): the width's share may give that parameter a std, and its correlations are
        # decided again from the widened stds.
        formed = np.all(np.isfinite(cat["std"]), axis=-1)[:, None, None]
        corr_in = np.where(formed & np.isnan(cat["corr"]), 0.0, cat["corr"])
        cat["std"], corr_w, width = widen(
            fitter.space,
            fitter.pooled.alpha,
            cat["theta"],
            cat["std"],
            corr_in,
            cat["width_v"],
            cat["width_s"],
        )
        cat["corr"], cat["flag"] = undefined_correlations(cat["std"], corr_w, cat["flag"])
    maps = _maps(fitter, cat, h, w, width)
    report = _report(fitter, cat, capture, job, maps, compile_s, times, len(tiles), loaded)
    if width is not None:
        report["pooled"]["width_laplace"] = width.as_dict()
    report["timings"]["stages_s"] = dict(fitter.stage_s)
    report["timings"]["choose_s"] = choose_s
    report["timings"]["light_s"] = light_s
    report["light"] = light.as_dict()
    if per_process is not None:
        _distributed_timings(report, per_process, h * w * len(missing) / len(tiles))
    report["auto"] = None if choice is None else choice.as_dict()
    return CaptureFit(
        maps=maps,
        report=report,
        labels=fitter.space.labels,
        theta=cat["theta"],
        job=job,
        tiles_computed=len(todo),
        tiles_loaded=loaded,
        extra={
            "channels": c,
            "sse": cat["sse"],
            "cnt": cat["cnt"],
            "alpha_min": fitter.alpha_min,
            "noise_estimated": fitter.estimates_noise,
            "pooled": fitter.pooled,
            "auto": choice,
        },
    )


def _collect(tdir, tiles, results, computed: int, compile_s: float, run_s: float) -> np.ndarray:
    """Wait for every process's tiles, read those of the others into ``results``; returns
    (processes, 3): tiles computed, compile seconds, run seconds of each process."""
    process_barrier("jaxrefl fit: tiles written")
    for i, r in enumerate(results):
        if r is None:
            s, e = tiles[i]
            results[i] = _load_tile(tdir / f"tile_{i:05d}.npz", e - s)
            if results[i] is None:
                raise RuntimeError(
                    f"{tdir}/tile_{i:05d}.npz: missing or unreadable after every process "
                    "finished; is the output folder one shared folder for all processes?"
                )
    stats = np.array([computed, compile_s, run_s], np.float64)
    return process_gather(stats, "jaxrefl fit: timings gathered")


def _distributed_timings(report: dict, per: np.ndarray, pixels: float) -> None:
    """The report's timings of a multi-process fit: per process (``processes``), and the
    job's ``run_s`` as the slowest process's, its ``pixels_per_s`` over all processes."""
    t = report["timings"]
    run_s = float(np.max(per[:, 2]))
    t["processes"] = {
        "count": int(per.shape[0]),
        "tiles_computed": [int(v) for v in per[:, 0]],
        "compile_s": per[:, 1].tolist(),
        "run_s": per[:, 2].tolist(),
    }
    t["run_s"] = run_s
    t["compile_s"] = float(np.max(per[:, 1]))
    t["pixels_per_s"] = pixels / run_s if run_s > 0 else None


def _maps(
    fitter: _TileFitter, cat, h: int, w: int, width: WidthUncertainty | None = None
) -> dict[str, np.ndarray]:
    space = fitter.space
    theta = cat["theta"]
    ok = np.all(np.isfinite(theta), axis=-1)
    nat = np.asarray(space.natural_vector(jnp.asarray(np.where(ok[:, None], theta, 0.0))))
    nat = np.where(ok[:, None], nat, np.nan)
    maps: dict[str, np.ndarray] = {}
    labels = space.labels
    for j, lab in enumerate(labels):
        maps[map_name(lab)] = nat[:, j]
        maps[map_name(lab, "_std")] = cat["std"][:, j]
    if "alpha" in labels:
        j = labels.index("alpha")
        root = np.sqrt(np.maximum(nat[:, j], 0.0))
        maps["roughness"] = root
        # d sqrt(alpha) / d alpha = 1 / (2 sqrt(alpha)): the delta method, as for every map.
        slope = np.where(root > 0, 2.0 * root, np.nan)
        maps[map_name("roughness", "_std")] = cat["std"][:, j] / slope
    if fitter.pooled is not None and fitter.pooled.alpha is not None:
        # The shared width: one value, the same map everywhere a pixel has an estimate.
        shared = np.where(ok, fitter.pooled.alpha, np.nan)
        maps["alpha"] = shared
        maps["roughness"] = np.sqrt(shared)
        if width is not None:
            # Its Laplace std (_shared), by the delta method for roughness = sqrt(alpha).
            maps[map_name("alpha", "_std")] = np.where(ok, width.alpha_std, np.nan)
            maps[map_name("roughness", "_std")] = np.where(
                ok, width.alpha_std / (2.0 * np.sqrt(fitter.pooled.alpha)), np.nan
            )
    spec = [j for j, lab in enumerate(labels) if lab.startswith("specular.")]
    alb = [j for j, lab in enumerate(labels) if lab.startswith("albedo.")]
    if len(spec) > 1 and len(spec) == len(alb):
        # The metallic-roughness view of a coloured specular (glTF 2.0; brdf._convert).
        base_j, metal = brdf.specular_to_metallic(
            jnp.asarray(np.nan_to_num(nat[:, alb])), jnp.asarray(np.nan_to_num(nat[:, spec]))
        )
        base = np.where(ok[:, None], np.asarray(base_j), np.nan)
        for j, lab in zip(range(base.shape[1]), [labels[i] for i in alb], strict=True):
            maps["base_color." + lab.split(".", 1)[1]] = base[:, j]
        maps["metallic"] = np.where(ok, np.asarray(metal), np.nan)
    if "tilt_x" in labels:
        tx, ty = nat[:, labels.index("tilt_x")], nat[:, labels.index("tilt_y")]
        n = np.asarray(brdf.tilt_normal(jnp.asarray(tx), jnp.asarray(ty)))
        for j, axis in enumerate("XYZ"):
            maps[f"normal.{axis}"] = n[:, j]
    for a in range(len(labels)):
        for b in range(a + 1, len(labels)):
            maps[corr_name(labels[a], labels[b])] = cat["corr"][:, a, b]
    maps["status"] = cat["status"].astype(np.uint32)
    maps["laplace_flag"] = cat["flag"].astype(np.uint32)
    maps["noise_std"] = np.sqrt(cat["noise_var"])
    maps["cost"] = cat["cost"]
    maps["n_used"] = cat["n_used"].astype(np.uint32)
    maps["iterations"] = cat["iterations"].astype(np.uint32)
    maps["misspecified"] = _model_check(fitter, cat).astype(np.uint32)
    return {
        k: np.asarray(v).reshape(h, w).astype(v.dtype if v.dtype == np.uint32 else np.float32)
        for k, v in maps.items()
    }


def _model_check(fitter: _TileFitter, cat) -> np.ndarray:
    """(N,) :class:`ModelCheck` bits of the fit (:mod:`jaxrefl.svbrdf._check`): the bound
    check, and for Gaussian noise the check of the training photos' squared errors against
    the capture's noise variance (the median over pixels, in radiance units)."""
    theta = cat["theta"]
    ok = np.all(np.isfinite(theta), -1)
    dn = np.abs(np.asarray(fitter.space.dnatural(jnp.asarray(np.where(ok[:, None], theta, 0.0)))))
    with np.errstate(divide="ignore", invalid="ignore"):
        theta_std = cat["std"] / dn  # the delta method reversed (laplace_theta_std)
    check = bound_bits(fitter.space, theta, theta_std)
    if not isinstance(fitter.noise, fit.GaussianNoise):
        return check
    var = np.asarray(cat["noise_var"], np.float64)
    if fitter.known_noise is None and fitter.noise.sigma is not None:
        # the estimated scale multiplies the model's variance (its mean over channels)
        var = var * float(np.mean(np.asarray(fitter.noise.sigma, np.float64) ** 2))
    good = var[np.isfinite(var) & (var > 0)]
    if good.size == 0:
        return check
    train = fitter.train
    chi2 = np.sum(cat["sse"][:, train], axis=1) / float(np.median(good))
    dof = np.sum(cat["cnt"][:, train], axis=1) - fitter.space.size
    return check | np.where(ppc_failed(chi2, dof), int(ModelCheck.PPC_FAILED), 0)


def _rmse(sse: np.ndarray, cnt: np.ndarray) -> float | None:
    n = float(np.sum(cnt))
    return float(np.sqrt(np.sum(sse) / n)) if n > 0 else None


def _report(fitter, cat, capture, job, maps, compile_s, times, n_tiles, loaded) -> dict:
    from jaxrefl import __version__

    k, h, w, c = capture.shape
    run_s = float(np.sum(times))
    n_px = h * w
    sse, cnt = cat["sse"], cat["cnt"]
    holdout = list(job.holdout)
    train = [i for i in range(k) if i not in holdout]
    report: dict[str, Any] = {
        "jaxrefl": __version__,
        "model": job.model,
        "model_description": type(fitter.model).__name__,
        "parameters": list(fitter.space.labels),
        "bounds": {
            lab: [float(lo), float(hi)]
            for lab, lo, hi in zip(
                fitter.space.labels, fitter.space.lower, fitter.space.upper, strict=True
            )
        },
        "alpha_min": fitter.alpha_min if "alpha" in fitter.space.labels else None,
        "pooled": None if fitter.pooled is None else fitter.pooled.as_dict(),
        "job": job.to_json(),
        "capture": {
            "layout": capture.layout,
            "source": None if capture.source is None else str(capture.source),
            "photos": k,
            "height": h,
            "width": w,
            "channels": c,
            "observations": capture.summary(),
        },
        "pixels": n_px,
        "status_counts": fit.describe(maps["status"]),
        "laplace_flag_counts": fit.flag_counts(maps["laplace_flag"]),
        # Pixels whose model cannot be right (jaxrefl.svbrdf._check): their Laplace and
        # predictive intervals are not calibrated.
        "misspecified_counts": check_counts(maps["misspecified"]),
        "timings": {
            "compile_s": compile_s,
            "run_s": run_s,
            "pixels_per_s": (n_px * (n_tiles - loaded) / n_tiles) / run_s if run_s > 0 else None,
            "tiles": n_tiles,
            "tiles_loaded": loaded,
            "tile_pixels": job.tile_pixels,
            "devices": jax.device_count(),  # of every process
            "platform": jax.devices()[0].platform,
        },
        "train_rmse": _rmse(sse[:, train], cnt[:, train]),
        "units": "radiance in the capture's linear units; albedo, specular: 1; alpha: GGX width",
    }
    if holdout:
        report["holdout"] = holdout
        report["heldout_rmse"] = _rmse(sse[:, holdout], cnt[:, holdout])
        report["heldout_rmse_per_photo"] = {str(i): _rmse(sse[:, i], cnt[:, i]) for i in holdout}
        report["heldout_observations"] = int(np.sum(cnt[:, holdout]))
        # A robust companion of the RMSE: a few pixels with wild predictions (e.g. a lobe
        # aimed where the training photos were clipped) dominate the RMSE, not the median.
        n_h = np.sum(cnt[:, holdout], axis=1)
        per_px = np.sqrt(np.sum(sse[:, holdout], axis=1)[n_h > 0] / n_h[n_h > 0])
        report["heldout_pixel_rmse_median"] = float(np.median(per_px)) if per_px.size else None
        report["heldout_pixel_rmse_p99"] = float(np.quantile(per_px, 0.99)) if per_px.size else None
    return report


def status_meanings() -> dict[str, str]:
    """Readable meanings of the ``status`` map's codes."""
    return {str(int(s)): f"{s.name}: {fit.STATUS_MEANINGS[s]}" for s in Status}
