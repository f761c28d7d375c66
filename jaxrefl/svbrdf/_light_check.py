"""The light ``auto`` keeps, checked by the model a job names.

``auto`` (:func:`jaxrefl.svbrdf.estimate_light`) judges the light under one GGX width shared
by every pixel (the ``pooled`` model's lobe): a score whose predictions of unseen photos
stay bounded, so that it measures the light. A job that names its model is then fitted with
that model under the light kept, and what helps the shared width need not help another
model: a per-pixel lobe fitted to the tails of highlights extrapolates into a highlight no
training photo showed, and where those blunders fall moves with the light. So where the job
names a model (not ``auto``, whose choice is scored under the light kept) and ``auto`` kept
an estimate, that model scores the estimate against the stated light by what ``auto``'s
model choice scores models with (:func:`jaxrefl.svbrdf.choose_model`): leave-one-photo-out
over the job's training photos on a random pixel sample, each fold's photo predicted by the
model fitted on the others with the job's settings. The estimate is kept only where the
model's held-out RMSE under it is not above its RMSE under the stated light; otherwise the
light goes back to ``fixed``, and ``why`` says so. The held-out photo of each fold is
predicted at its prior gain (the estimate's gain of a photo comes from that photo: scoring
it there would credit the gains with what no unseen photo gets), as in ``auto``'s own score.

The check scores the estimate ``auto`` kept, not the simpler one it kept it over: where the
model rejects ``offset+gains``, the light is ``fixed``, not ``offset``.
"""

from __future__ import annotations

from dataclasses import replace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._auto import photos_needed
from ._data import stack_folds, subsample
from ._job_types import FitJob
from ._light import LightEstimate, fixed_light
from ._tile_fitter import TileFitter

__all__ = ["check_light"]


def _loo_sse(capture, job: FitJob, train: list[int], n_pixels: int, seed: int, gain_ratio):
    """The job's model's leave-one-photo-out squared error and count over ``train`` on
    ``n_pixels`` random pixels of ``capture`` (the same pixels for every capture of one shape
    and seed); photo j's prediction in its own fold scaled by ``gain_ratio[j]``."""
    k = capture.n_photos
    data = subsample(capture, n_pixels, seed, job.dtype)
    size = job.tile_pixels
    stacked, mask, held = stack_folds(data, train, k, size)
    rows = np.flatnonzero(held >= 0)
    factor = np.ones(stacked.scale.shape[:2])
    factor[rows, held[rows]] = np.asarray(gain_ratio)[held[rows]]
    f = jnp.asarray(factor, stacked.scale.dtype)[..., None]
    stacked = eqx.tree_at(lambda d: d.scale, stacked, stacked.scale * f)
    fitter = TileFitter(capture, job, width_terms=False)
    sse = cnt = 0.0
    for s in range(0, mask.shape[0], size):
        part = slice(s, s + size)
        e, c, _r, _d = fitter.score(jax.tree.map(lambda a, p=part: a[p], stacked), mask[part])
        h = held[part]
        live = np.flatnonzero(h >= 0)
        sse += float(np.sum(e[live, h[live]]))
        cnt += float(np.sum(c[live, h[live]]))
    return sse, cnt


def check_light(capture, estimate: LightEstimate, job: FitJob) -> LightEstimate:
    """``estimate`` (``auto``'s, of ``capture`` as its files state the light) where the model
    ``job`` names predicts the training photos held out in turn at least as well under it as
    under the stated light, else the stated light (module docstring). Returned unchanged
    where the job's model is ``auto``, the light was asked for by name, or ``auto`` kept
    ``fixed``; and where the training photos are too few to score the model, with ``why``
    saying so. The pixels are sampled as the model choice samples them (``job.auto``: its
    pixel count and seed)."""
    if job.model == "auto" or estimate.asked != "auto" or estimate.mode == "fixed":
        return estimate
    k = capture.n_photos
    train = [i for i in range(k) if i not in job.holdout]
    need = photos_needed(job.model, capture.shape[-1], job.alpha_min)
    if need > len(train) - 1:
        return replace(
            estimate,
            why=f"{estimate.why}; not checked with {job.model}: each leave-one-out fold "
            f"trains on {len(train) - 1} photos and it needs {need}",
        )
    n_pixels = max(256, job.auto.max_pixels // len(train))
    seed = job.auto.seed
    ones = np.ones(k)
    prior = np.ones(k) if estimate.prior is None else np.exp(estimate.prior.log_mean)
    sse_f, cnt_f = _loo_sse(capture, job, train, n_pixels, seed, ones)
    lit = estimate.apply(capture)
    sse_l, cnt_l = _loo_sse(lit, job, train, n_pixels, seed, prior / estimate.photo_gain)
    rmse = {
        "fixed": float(np.sqrt(sse_f / cnt_f)) if cnt_f > 0 else float("inf"),
        estimate.mode: float(np.sqrt(sse_l / cnt_l)) if cnt_l > 0 else float("inf"),
    }
    account = (
        f"{job.model}'s leave-one-photo-out RMSE over {len(train)} training photos: "
        f"{estimate.mode} {rmse[estimate.mode]:.5f}, fixed {rmse['fixed']:.5f}"
    )
    if rmse[estimate.mode] <= rmse["fixed"]:
        return replace(estimate, why=f"{estimate.why}; kept by {account}", model_cv_rmse=rmse)
    kept = fixed_light(
        capture,
        estimate.asked,
        f"{estimate.why}; the stated light instead: {account} (the estimate helps the "
        f"shared width's predictions, not {job.model}'s)",
    )
    # auto's problem goes with it: the map's lens-position spread draws from its offset.
    return replace(
        kept,
        cv_rmse=estimate.cv_rmse,
        prior=estimate.prior,
        model_cv_rmse=rmse,
        offset_source=estimate.offset_source,
    )
