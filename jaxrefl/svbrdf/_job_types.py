"""The capture job's types: what to fit (:class:`FitJob`) and what came out (:class:`CaptureFit`).

They live apart from :func:`jaxrefl.svbrdf.fit_capture`, so that the modules that run a job
(the tile fitter, the model selection) and those that read its result (outputs, uncertainty,
planning) import the types and never each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import jax.numpy as jnp
import numpy as np

from jaxrefl import brdf, fit
from jaxrefl._errors import JaxreflError
from jaxrefl._names import LIGHT_CHOICES, LIGHT_DEFAULT, NOISE_LEVELS

from ._auto_options import AutoOptions
from ._models import ALPHA_RANGE, capture_model

if TYPE_CHECKING:
    from ._auto import ModelChoice
    from ._light import LightEstimate
    from ._pooled import PoolChoice

__all__ = ["COMPACT_MIN_PIXELS", "DEFAULT_LOSS", "CaptureFit", "FitJob"]

# Where ``FitJob.compact`` is None, captures of fewer pixels than this are fitted by the lean
# LM in one plain loop of steps rather than in compaction stages
# (fit.LMOptions.compact_stages): each stage is one more compiled copy of the LM step, and
# the steps it saves repay that compile only over some tens of tiles of the default size.
COMPACT_MIN_PIXELS = 1 << 17

# Models whose default loss is not L2. Huber's threshold is one noise std (the pooled model
# estimates that std): a glint or a misregistered edge in one photo then pulls the shared
# lobe and the pixel's F0 linearly, not quadratically.
DEFAULT_LOSS: dict[str, fit.Loss] = {"pooled": fit.Huber()}
_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))


@dataclass(frozen=True)
class FitJob:
    """What to fit and how (everything that changes the result; see
    :func:`jaxrefl.svbrdf.fit_capture`).

    model:      a name of :data:`jaxrefl.svbrdf.CAPTURE_MODELS`, or ``auto`` (the default):
                the candidate that best predicts held-out training photos
                (:func:`jaxrefl.svbrdf.choose_model`; the report's ``auto`` says why)
    holdout:    photo indices left out of the fit and used to measure prediction error
    tile_pixels: pixels per tile (memory is constant in the image size, about 1 kB a pixel)
    config:     a :class:`jaxrefl.fit.FitConfig`:

                * ``solver``: :class:`~jaxrefl.fit.LMOptions` (default), or a library solver
                  (:class:`~jaxrefl.fit.OptimistixLM`, :class:`~jaxrefl.fit.JaxoptLM`),
                  with its iteration budget (the lean LM's compaction stages as
                  ``compact`` says)
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
    light:      the flash as the capture states it (``fixed``), or estimated first
                (:func:`jaxrefl.svbrdf.estimate_light`): ``offset`` (its offset from the
                lens), ``offset+gains`` (and a gain per photo), ``auto`` (whichever
                held-out observations support); default ``jaxrefl._names.LIGHT_DEFAULT``,
                also ``jaxrefl fit``'s and ``jaxrefl sample``'s; the report's ``light``
                says what and why
    compact:    whether the lean LM gathers its slow pixels into compaction stages
                (:attr:`jaxrefl.fit.LMOptions.compact_stages`), in the fit and in the model
                selection; False runs one plain loop of steps (the stages dropped). Per-pixel
                results do not depend on it: it trades compiled copies of the step for the
                steps they save. None (the
                default): the size rule, stages where the capture has
                :data:`COMPACT_MIN_PIXELS` pixels or more (:meth:`compacts`);
                :func:`~jaxrefl.svbrdf.fit_capture` records the value it ran with
    noise_level: ``auto`` (default): where the noise model is the default flat one and the
                model is a per-pixel one, a capture-wide noise-level function (std growing
                with the signal; :func:`jaxrefl.svbrdf.estimate_noise_level`) replaces it if
                the residuals support it (the report's ``noise_level`` says what and why);
                ``flat``: keep the flat one
    auto:       how ``auto`` chooses the model (:class:`~jaxrefl.svbrdf.AutoOptions`: the
                candidates, the selection's pixel count and seed); recorded with the job
                whatever the model, since ``pooled``'s shared width where it wins is the
                selection's
    """

    model: str = "auto"
    holdout: tuple[int, ...] = ()
    tile_pixels: int = 4096
    config: fit.FitConfig = field(default_factory=fit.FitConfig)
    alpha_min: float | None = None
    tilt_std: float = 0.1
    light: str = LIGHT_DEFAULT
    compact: bool | None = None
    auto: AutoOptions = field(default_factory=AutoOptions)
    noise_level: str = NOISE_LEVELS[0]

    def __post_init__(self) -> None:
        if self.noise_level not in NOISE_LEVELS:
            raise JaxreflError(
                f"FitJob.noise_level must be one of {', '.join(NOISE_LEVELS)}, "
                f"not {self.noise_level!r}"
            )
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
        if self.compact not in (None, True, False):
            raise JaxreflError(f"compact must be True, False or None, not {self.compact!r}")
        if self.compact is not None:
            object.__setattr__(self, "compact", bool(self.compact))
        if not isinstance(self.auto, AutoOptions):
            raise JaxreflError(
                f"FitJob.auto must be an AutoOptions, not {type(self.auto).__name__}"
            )

    def compacts(self, n_pixels: int) -> bool:
        """Whether the lean LM runs compaction stages for a capture of ``n_pixels`` pixels
        (fitted ``n_pixels`` at a time or, over several folds, in all): ``compact``, or
        where it is None the size rule (:data:`COMPACT_MIN_PIXELS`)."""
        return n_pixels >= COMPACT_MIN_PIXELS if self.compact is None else self.compact

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
            "compact": self.compact,
            "auto": self.auto.to_json(),
            "noise_level": self.noise_level,
        }


@dataclass
class CaptureFit:
    """Result of :func:`jaxrefl.svbrdf.fit_capture`: maps (H, W) by channel name, and a report.

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
    light:   the light the pixels were fitted under (:class:`jaxrefl.svbrdf.LightEstimate`;
             ``light.apply(capture)`` places it); None: as the capture states it
    channels: colour channels C of the capture the model was built for
    alpha_min: the lower bound of the lobe width alpha the model was built with (the job's
             ``alpha_min``, or the training photos' resolvable width); None: the model's own
    pooled:  ``pooled``'s choice (shared width, F0 prior, noise sigma); None for the other
             models
    noise_estimated: whether the Laplace step estimated each pixel's noise scale from its
             residuals (False where it is known: ``pooled``'s capture-wide scale, or a
             two-stage model's first-stage median)
    sse, cnt: (H*W, K) per pixel and photo, the sum of squared radiance errors and the count
             of the observations that are values (held-out photos included); None for a
             fit read back from its files
    auto:    the model choice by held-out photos (``FitJob(model="auto")``); None otherwise
    """

    maps: dict[str, np.ndarray]
    report: dict[str, Any]
    labels: tuple[str, ...]
    theta: np.ndarray  # (H*W, P)
    job: FitJob
    tiles_computed: int = 0
    tiles_loaded: int = 0
    light: LightEstimate | None = None
    channels: int = 3
    alpha_min: float | None = None
    pooled: PoolChoice | None = None
    noise_estimated: bool = True
    sse: np.ndarray | None = None
    cnt: np.ndarray | None = None
    auto: ModelChoice | None = None

    def model(self) -> tuple[brdf.BRDF, Any]:
        """(model, parameter space) the pixels were fitted with (for ``pooled``: the shared
        alpha of :attr:`pooled`)."""
        return capture_model(
            self.job.model,
            channels=self.channels,
            alpha_min=self.alpha_min,
            alpha=None if self.pooled is None else self.pooled.alpha,
        )

    def params(self) -> dict[str, np.ndarray]:
        """Natural parameters as (H, W, ...) arrays for ``model.eval``."""
        _model, space = self.model()
        h, w = self.maps["status"].shape
        t = jnp.asarray(np.nan_to_num(self.theta), dtype=self.job.dtype)
        nat = space.to_natural(t)
        return {k: np.asarray(v).reshape(h, w, *v.shape[1:]) for k, v in nat.items()}
