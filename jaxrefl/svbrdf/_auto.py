"""Choosing a capture's model by held-out photos: add what the scene needs, leave out the rest.

``FitJob(model="auto")`` (the default) fits a capture with whichever candidate of
``FitJob.auto.candidates`` (:class:`~jaxrefl.svbrdf.AutoOptions`; default
:data:`~jaxrefl.svbrdf.AUTO_CANDIDATES`) predicts photos it was not fitted to best:

* ``lambert``: diffuse only;
* ``ggx``: a dielectric (grey F0 in [0, 0.25]) with a per-pixel lobe;
* ``ggx_rgb``: a coloured specular (F0 per channel in [0, 1], metals) with a per-pixel lobe;
* ``pooled``: the coloured specular with one lobe width for the capture and pooled F0
  (:mod:`jaxrefl.svbrdf._pooled`);
* ``ggx_normal``: the dielectric with a per-pixel shading normal, tried only where the
  per-pixel dielectric is the best so far (:data:`REFINES`) and a score test of the slopes
  at its optimum finds them (:data:`EVIDENCE_RATIO`, :mod:`jaxrefl.svbrdf._score_test`):
  the refinement's fit costs more than all the other candidates together, and on a flat
  surface it buys nothing.

The score is the leave-one-photo-out RMSE over the *training* photos (the job's own
``holdout`` photos are never looked at, so a held-out figure of an ``auto`` fit stays an
honest one): for each training photo j, every candidate is fitted on the other training
photos and predicts photo j's uncensored observations; the squared errors of all folds are
summed. The folds share one random set of pixels (a paired comparison: every candidate is
scored on the same observations; ``AutoOptions.max_pixels`` and ``seed``), and they are
stacked into the rows of tiles of the job's tiling (one tile at the defaults), each row with
its own training photos, and the chosen model's compiled programs serve the full fit too.
``pooled``'s shared width and F0 prior are chosen once from all training photos (one scalar
and a per-channel prior, fitted to every selection pixel; the per-pixel parameters are
fitted per fold).

The winner is the first candidate (in the candidates' order, simplest first) whose
score is within :data:`TOLERANCE` (relative) of the lowest: the ranking is a measurement, and
a difference smaller than the folds' scatter is not evidence for extra parameters. The
report's ``auto`` entry lists every candidate's score and says why the winner won.

Small captures: a model can be fitted to a pixel only where its photos give at least as many
observations (C per photo) as the model has per-pixel parameters (:func:`photos_needed`;
``pooled`` also needs two photos to choose its width), and it can be scored only where each
leave-one-out fold (one training photo fewer) can fit it. Candidates that cannot be fitted
or scored are listed in ``skipped`` with the photos they need; with nothing left to score
the choice is the simplest candidate that can be fitted (``why`` says so), and with nothing
that can be fitted :func:`choose_model` refuses, listing what each candidate needs.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from typing import Any

import jax
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl._threads import threaded

from ._auto_options import AUTO_CANDIDATES, SELECTION_PIXELS, AutoOptions
from ._data import stack_folds, subsample
from ._job_types import FitJob
from ._models import capture_model
from ._pooled import PoolChoice
from ._tile_fitter import TileFitter

# AUTO_CANDIDATES and SELECTION_PIXELS are the defaults of AutoOptions, named here too for
# the modules of this package that size their samples as the choice does.
__all__ = [
    "AUTO_CANDIDATES",
    "SELECTION_PIXELS",
    "TOLERANCE",
    "ModelChoice",
    "choose_model",
    "photos_needed",
]

# Candidates that refine another (name -> the model they extend) are scored only when that
# model is the best so far (a per-pixel normal on a lobe the photos do not support cannot
# help) and the photos show their extra parameters (EVIDENCE_RATIO).
REFINES: dict[str, str] = {"ggx_normal": "ggx"}
# Relative margin a more complex model must win by (see the module docstring).
TOLERANCE = 0.01
# A refinement is scored only where the score test of its extra parameters at the base
# model's optimum (:mod:`jaxrefl.svbrdf._score_test`) finds them: the statistic T summed over
# the selection must exceed its expectation E without them by EVIDENCE_Z null standard
# deviations and by the factor EVIDENCE_RATIO. The factor covers what the null's E leaves
# out: each pixel's noise scale is an estimate from a handful of residuals (its inverse,
# which weighs the score, is biased up by about 2 / dof), and a base model that misses
# some of the signal leaves residuals that any new direction picks up a little of.
EVIDENCE_Z = 3.0
EVIDENCE_RATIO = 1.5


@dataclass(frozen=True)
class ModelChoice:
    """What :func:`choose_model` chose, and the evidence.

    model:    the chosen candidate's name
    cv_rmse:  leave-one-photo-out RMSE of every candidate over the training photos
    pixels:   pixels of the selection sample (each scored once per fold)
    folds:    the training photos scored, each held out once
    skipped:  candidates not scored, with the reason (:data:`REFINES`)
    pooled:   ``pooled``'s own choice (width, F0 prior) on the same training photos, which
              the fit reuses when ``pooled`` wins
    evidence: per refinement tested, its score statistic over that statistic's expectation
              where the refinement is not needed (:data:`EVIDENCE_RATIO`)
    note:     why no candidate was scored, where none was (too few training photos)
    options:  the settings of the choice (``FitJob.auto``)
    """

    model: str
    cv_rmse: dict[str, float]
    pixels: int
    folds: tuple[int, ...]
    skipped: dict[str, str]
    pooled: PoolChoice | None = None
    evidence: dict[str, float] = field(default_factory=dict)
    note: str | None = None
    options: AutoOptions = field(default_factory=AutoOptions)

    def as_dict(self) -> dict[str, Any]:
        ranked = sorted(self.cv_rmse.items(), key=lambda kv: kv[1])
        lam = self.cv_rmse.get("lambert")
        scored = [r for r in self.cv_rmse.values() if np.isfinite(r)]
        if self.note is not None:
            why = self.note
        elif not scored:
            # Every fold's held-out observations censored, masked or unpredicted.
            why = (
                f"no candidate could be scored: over {len(self.folds)} training photos, no "
                "held-out photo has a measured (uncensored, unmasked) observation that a fit "
                f"on the others predicts; chose the simplest, {self.model}"
            )
        else:
            why = f"lowest leave-one-photo-out RMSE over {len(self.folds)} training photos: " + (
                ", ".join(f"{m} {r:.5f}" for m, r in ranked)
            )
        if self.note is None and scored and lam is not None and self.model != "lambert":
            why += f" ({self.cv_rmse[self.model] / lam:.2f} x Lambert's)"
        return {
            "model": self.model,
            "why": why,
            "cv_rmse": dict(self.cv_rmse),
            "selection_pixels": self.pixels,
            "folds": list(self.folds),
            "skipped": dict(self.skipped),
            "evidence": dict(self.evidence),
            "tolerance": TOLERANCE,
            **self.options.to_json(),
        }


def _photos(n: int) -> str:
    return f"{n} photo" if n == 1 else f"{n} photos"


def photos_needed(model: str, channels: int, alpha_min: float | None = None) -> int:
    """The fewest photos that pose ``model``'s per-pixel fit: as many observations (``channels``
    per photo) as per-pixel parameters; ``pooled`` (albedo and F0 per channel, one shared
    width) also needs two to choose its width by held-out error."""
    if model == "pooled":
        # 2 C observations for albedo and F0, and a second photo to score the width by.
        return 2
    _, space = capture_model(model, channels=channels, alpha_min=alpha_min)
    return -(-space.size // channels)


def choose_model(capture, job: FitJob) -> ModelChoice:
    """Score every candidate of ``job.auto`` (:class:`~jaxrefl.svbrdf.AutoOptions`: the
    candidates, the selection's pixel count and seed) by leave-one-photo-out over the photos
    ``job`` trains on (module docstring) and choose one. ``job`` gives everything but the
    model (noise, loss -- None: each model's default --, dtype, alpha_min, tiling, the
    choice's settings). Candidates the training photos
    cannot fit or score are skipped (module docstring, "Small captures"); where none can be
    fitted a :class:`~jaxrefl.JaxreflError` lists what each needs. The per-pixel fits gather
    their slow pixels into the lean LM's compaction stages as the fit does (``job.compact``,
    :meth:`FitJob.compacts`: the selection's tiles have the fit's shape, so they share its
    compiled programs)."""
    opts = job.auto
    candidates = opts.candidates
    k = capture.n_photos
    train = [i for i in range(k) if i not in job.holdout]
    n = len(train)
    if n == 0:
        raise JaxreflError("every photo is held out: nothing left to fit")
    need = {m: photos_needed(m, capture.shape[-1], job.alpha_min) for m in candidates}
    fits = [m for m in candidates if need[m] <= n]
    if not fits:
        raise JaxreflError(
            f"auto: no candidate model can be fitted to the {_photos(n)} of "
            f"{capture.source or 'this capture'} it trains on: "
            + ", ".join(f"{m} needs {need[m]}" for m in candidates)
            + "; add photos or hold fewer out"
        )
    # Each leave-one-out fold trains on one photo fewer.
    scorable = [m for m in fits if need[m] <= n - 1]
    skipped: dict[str, str] = {
        m: f"needs {need[m]} training photos, the capture has {_photos(n)}"
        for m in candidates
        if m not in fits
    }
    skipped.update(
        {
            m: f"can be fitted to {_photos(n)} but not scored: each leave-one-out fold trains "
            f"on {_photos(n - 1)} and it needs {need[m]}"
            for m in fits
            if m not in scorable
        }
    )
    if not scorable:
        note = (
            f"too few training photos ({n}) to score any candidate by leave-one-out; "
            f"{', '.join(fits)} can be fitted, and the simplest, {fits[0]}, is chosen"
        )
        return ModelChoice(fits[0], {}, 0, tuple(train), skipped, note=note, options=opts)
    # Fewer pixels a fold than this would leave each fold's score to a handful of pixels.
    per_fold = max(256, opts.max_pixels // len(train))
    data = subsample(capture, per_fold, opts.seed, job.dtype)
    size = job.tile_pixels
    stacked, mask, held = stack_folds(data, train, k, size)
    cv: dict[str, float] = {}
    evidence: dict[str, float] = {}
    bases = set(REFINES.values())

    def score(m: str, fitter=None):
        """(fitter, leave-one-photo-out RMSE, the fits of each tile of rows where a
        refinement starts from ``m``'s)."""
        if fitter is None:
            fitter = TileFitter(capture, replace(job, model=m), width_terms=False)
        sse = cnt = 0.0
        fits = []
        for s in range(0, mask.shape[0], size):
            part = slice(s, s + size)
            e, c, r, d = fitter.score(jax.tree.map(lambda a, p=part: a[p], stacked), mask[part])
            if m in bases:
                fits.append((r, d))
            h = held[part]
            rows = np.flatnonzero(h >= 0)
            sse += float(np.sum(e[rows, h[rows]]))
            cnt += float(np.sum(c[rows, h[rows]]))
        return fitter, float(np.sqrt(sse / cnt)) if cnt > 0 else float("inf"), fits

    # The candidates that refine none are independent: they are scored side by side (most of
    # their time is compiling their programs, which runs on one core each).
    plain = [m for m in scorable if m not in REFINES]
    # One thread a candidate, up to the cores; a pool and a window need at least one (a
    # window of every candidate starts them all at once).
    threads = max(1, min(len(plain), os.cpu_count() or 1))
    scores = threaded(score, plain, threads, max(1, len(plain)), wait=True)
    done = dict(zip(plain, scores, strict=True))
    pool: PoolChoice | None = done["pooled"][0].pooled if "pooled" in done else None
    cv.update({m: done[m][1] for m in plain})
    for m in scorable:
        base = REFINES.get(m)
        if base is None:
            continue
        if base in cv and cv[base] > min(cv.values()) * (1.0 + TOLERANCE):
            skipped[m] = f"refines {base}, which is not the best so far"
            continue
        fitter = TileFitter(capture, replace(job, model=m), width_terms=False)
        if base in done:
            ev = np.sum([fitter.tilt_evidence(r, d) for r, d in done[base][2]], axis=0)
            t, e, v = (float(x) for x in ev)
            evidence[m] = t / e if e > 0 else float("inf")
            if t <= e + EVIDENCE_Z * np.sqrt(v) or evidence[m] < EVIDENCE_RATIO:
                skipped[m] = (
                    f"refines {base}, and the training photos show no sign of it at {base}'s "
                    f"optimum: score statistic {evidence[m]:.2f} x its expectation without it"
                )
                continue
        cv[m] = score(m, fitter)[1]
    best = min(cv.values())
    chosen = next(m for m in candidates if cv[m] <= best * (1.0 + TOLERANCE))
    return ModelChoice(
        chosen, cv, int(data.obs.shape[0]), tuple(train), skipped, pool, evidence, options=opts
    )
