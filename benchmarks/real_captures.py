"""Real flash captures: how well each model predicts the photos it was not fitted to.

For ``bath_tile`` and ``yellow_box`` (``../shared/data/svbrdf_flash``, read at 256 x 256
by default), every photo is held out in turn (:func:`jaxrefl.svbrdf.leave_one_out`) and
predicted by a fit on the other eight:

* ``lambert``: the diffuse-only baseline;
* ``ggx``: per-pixel GGX + Lambert with a grey (dielectric) F0;
* ``pooled``: one GGX width per capture, chosen by held-out photos, coloured F0 with an
  empirical-Bayes prior (:mod:`jaxrefl.svbrdf._pooled`);
* ``auto``: the default, ``FitJob(model="auto")``: in every fold, the model that best
  predicts the fold's own training photos held out in turn (:mod:`jaxrefl.svbrdf._auto`),
  its selection's time included (its first fold compiles every candidate);
* ``adam``: the per-pixel gradient-descent peer (``benchmarks/peer_adam.py``: the
  svbrdf-diff-renderer / MaterialGAN per-pixel mode, 1,000 Adam steps).

The flash is where the capture states it (``FitJob(light="fixed")``), as the peer takes
it; the light's estimate has its own column (below). Figures are over each held-out photo's
uncensored, valid observations, in linear radiance: the RMSE of each photo, their mean, and
the median and 99th percentile over pixels of the per-pixel held-out RMSE (all photos), in two
tables: jaxrefl's raw (unclipped) predictions, and every model's predictions clamped to
[0, 1], as a renderer displays them. The peer is scored in the clamped table only: its
renderer clamps before anyone sees its output, so that is what its users get (its raw
radiance is printed beside, for reference). The targets compare like with like: against
Lambert on raw predictions, against the peer with both clamped. Times: run seconds summed
over the folds, compilation apart, and process CPU seconds (both cores count) with
compilation apart too: the peer's around its compiled steps, jaxrefl's around the fits of a
second pass over the same folds (its selection included, every program compiled; that pass's
predictions give the clamped figures).

    python benchmarks/real_captures.py [--size 256] [--captures bath_tile,yellow_box]
        [--models lambert,ggx,pooled,auto,adam] [--adam-steps 1000] [--no-write]

It prints the tables and writes them, dated and with the machine, to the section
``real_captures`` of ``docs/benchmarks.md``.

The light column (``--light-only`` runs it alone, into the section
``real_captures_light``): every photo held out in turn, the ``--light-model`` fitted with
the flash as the capture states it (``FitJob(light="fixed")``), with each estimate forced in
every fold (``offset``, ``offset+gains``: :func:`jaxrefl.svbrdf.estimate_light` on the fold's
training photos; a held-out photo keeps its prior gain) and with ``light="auto"`` (an
estimate kept only where the fold's own training photos support it): the held-out RMSE of
each photo side by side, each against fixed's, the forced offsets with their reported std
(the Laplace's widened to the delete-one-photo jackknife's: :mod:`jaxrefl.svbrdf._light_cov`)
beside the spread of the folds' offsets, and what each fold's ``auto`` kept (the named model
checks its estimate: :mod:`jaxrefl.svbrdf._light_check`). Each photo's ratio to fixed has a
standard error from a paired spatial block bootstrap of its held-out squared errors (16 x 16
pixel blocks resampled with replacement, the same for both lights), and the photos worse or
better than fixed by more than two of them are named. The section is written after each
capture.

    python benchmarks/real_captures.py --light-only [--size 128] [--light-model pooled]
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
# Both sides run under XLA's default CPU emitters, not the loop emitters the command line
# (and _common) would choose: those serve jaxrefl's compile time (its own column), and the
# Adam peer's step programs run slower under them, so the peer is timed as it would run on
# its own (the header records the flags of each run).
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=true"
    ).strip()

from _common import flash_capture, machine, table, write_section  # noqa: E402

# The main table's light: the flash where the capture states it, as the peer takes it. The
# light's estimate is scored on its own (``--light-only``), and each fold's estimate would
# cost more than the models' fits.
MAIN_LIGHT = "fixed"


def _job(model: str):
    from jaxrefl.svbrdf import FitJob

    return FitJob(model=model, light=MAIN_LIGHT)


def _scores(cap, preds: dict[int, np.ndarray]) -> dict:
    """Held-out figures of each fold's prediction of its photo (K, H, W, C arrays by photo),
    raw and clamped to [0, 1]: RMSE per photo over its uncensored valid observations, and
    the median and 99th percentile over pixels of the per-pixel held-out RMSE."""
    k, h, w, _c = cap.shape
    out = {}
    for tag, clamp in (("raw", False), ("clamped", True)):
        per = np.full(k, np.nan)
        sse = np.zeros((h, w))
        cnt = np.zeros((h, w))
        for i, pred in preds.items():
            # What a renderer displays: radiance past the photo's white is shown as white.
            p = np.clip(pred, 0.0, 1.0) if clamp else pred
            use = (cap.status[i] == 0) & np.isfinite(p)
            e = np.where(use, p - cap.images[i], 0.0)
            per[i] = np.sqrt(np.sum(e * e) / max(np.sum(use), 1))
            sse += np.sum(e * e, axis=-1)
            cnt += np.sum(use, axis=-1)
        pix = np.sqrt(sse[cnt > 0] / cnt[cnt > 0])
        out[tag] = {
            "per_photo": per,
            "p50": float(np.median(pix)),
            "p99": float(np.quantile(pix, 0.99)),
        }
    return out


def _jaxrefl_folds(cap, job) -> tuple[dict, float]:
    """Every photo held out in turn, ``job`` fitted on the others (its programs compiled
    already): the scores of its predictions (:func:`_scores`) and the process CPU seconds of
    the fits alone (compilation apart, the predictions' rendering apart)."""
    from jaxrefl.svbrdf import fit_capture, predict_photos

    k, h, w, _c = cap.shape
    # As leave_one_out fits its folds: the K fits together decide the LM's compaction.
    job = replace(job, compact=job.compacts(k * h * w))
    cpu = 0.0
    preds = {}
    for i in range(k):
        c0 = time.process_time()
        fit = fit_capture(cap, replace(job, holdout=(i,)))
        cpu += time.process_time() - c0
        # predict_photos places the fit's light itself: it takes the capture as its files
        # state the light, as the fit did.
        preds[i] = predict_photos(fit, cap, [i])[1][0]
    return _scores(cap, preds), cpu


def _jaxrefl_model(cap, model: str) -> dict:
    from jaxrefl.svbrdf import leave_one_out

    job = _job(model)
    t0 = time.perf_counter()
    loo = leave_one_out(cap, job)
    wall = time.perf_counter() - t0
    # CPU seconds with compilation apart, as the peer's: the same folds again, every program
    # compiled; their predictions give the clamped figures.
    scores, cpu = _jaxrefl_folds(cap, job)
    r = loo.report
    own, base = float(np.sum(loo.fit_s)), float(np.sum(loo.baseline_fit_s))
    npx = cap.shape[1] * cap.shape[2] * cap.n_photos
    st, fl = r["fold_status_counts"], r["fold_laplace_flag_counts"]
    return {
        "per_photo": loo.per_photo,
        "p50": r["heldout_pixel_rmse_median"],
        "p99": r["heldout_pixel_rmse_p99"],
        "clamped": scores["clamped"],
        # leave_one_out's figures against the same folds' refit: the two passes agree.
        "refit_raw_gap": float(np.nanmax(np.abs(scores["raw"]["per_photo"] - loo.per_photo))),
        "run_s": own,
        "compile_s": loo.compile_s,
        "cpu_s": cpu,
        "wall_s": wall,
        "at_bound": st.get("AT_BOUND", 0) / npx,
        "not_identified": fl.get("NOT_IDENTIFIED", 0) / npx,
        "laplace_reliable": fl.get("reliable", 0) / npx,
        "pooled": r.get("pooled_per_fold"),
        "auto": r.get("auto_per_fold"),
        "lambert": {
            "per_photo": loo.baseline_per_photo,
            "p50": r["lambert_heldout_pixel_rmse_median"],
            "p99": r["lambert_heldout_pixel_rmse_p99"],
            "run_s": base,
            "compile_s": loo.baseline_compile_s,
        },
    }


def _adam(cap, steps: int) -> dict:
    from peer_adam import fit_peer

    k = cap.n_photos
    run_s = compile_s = cpu_s = 0.0
    preds = {}
    for i in range(k):
        fit = fit_peer(cap, holdout=(i,), steps=steps)
        preds[i] = fit.predict(cap)[i]
        run_s += fit.fit_s
        compile_s += fit.compile_s
        cpu_s += fit.cpu_s
    scores = _scores(cap, preds)
    return {
        **scores["raw"],
        "clamped": scores["clamped"],
        "run_s": run_s,
        "compile_s": compile_s,
        "cpu_s": cpu_s,
    }


def _fmt(x, nd=4):
    return "-" if x is None or not np.isfinite(x) else f"{x:.{nd}f}"


def _error_rows(results: dict, order: list[str], key: str | None) -> list[list[str]]:
    """Rows of held-out RMSE: raw figures (``key`` None) or ``results[m][key]``'s."""
    lam = results.get("lambert")
    lam = None if lam is None else (lam if key is None else lam.get(key))
    rows = []
    for m in order:
        r = results[m] if key is None else results[m].get(key)
        if r is None:
            continue
        mean = float(np.nanmean(r["per_photo"]))
        ratio = mean / float(np.nanmean(lam["per_photo"])) if lam else float("nan")
        rows.append(
            [
                m,
                *[_fmt(v) for v in r["per_photo"]],
                _fmt(mean),
                _fmt(ratio, 2),
                _fmt(r["p50"]),
                _fmt(r["p99"]),
            ]
        )
    return rows


def run_capture(name: str, size: int, models: list[str], adam_steps: int) -> tuple[str, dict]:
    cap = flash_capture(name, size)
    results: dict[str, dict] = {}
    for m in models:
        if m == "lambert":
            continue
        t0 = time.perf_counter()
        results[m] = _adam(cap, adam_steps) if m == "adam" else _jaxrefl_model(cap, m)
        print(f"  {name} {m}: {time.perf_counter() - t0:.0f} s", flush=True)
        if "lambert" not in results and "lambert" in results[m]:
            lam = dict(results[m]["lambert"])
            lam["cpu_s"] = None
            results["lambert"] = lam
    if "lambert" not in results and "lambert" in models:
        results["lambert"] = _jaxrefl_model(cap, "lambert")["lambert"]
    if "lambert" in results:
        results["lambert"]["clamped"] = _jaxrefl_folds(cap, _job("lambert"))[0]["clamped"]
    order = [m for m in ("lambert", "ggx", "pooled", "auto", "adam") if m in results]
    k = cap.n_photos
    headers = ["model", *[f"photo {i}" for i in range(k)], "mean", "/ Lambert", "p50 px", "p99 px"]
    t_rows = []
    for m in order:
        r = results[m]
        t_rows.append(
            [
                m,
                f"{r['run_s']:.1f}",
                f"{r['compile_s']:.1f}",
                "-" if r.get("cpu_s") is None else f"{r['cpu_s']:.0f}",
                _fmt(r.get("at_bound"), 3),
                _fmt(r.get("not_identified"), 3),
                _fmt(r.get("laplace_reliable"), 3),
            ]
        )
    raw_order = [m for m in order if m != "adam"]
    text = [
        f"**{name}**, {size} x {size}, {k} photos, each held out in turn, the flash as the "
        "capture states it (held-out RMSE, linear radiance).",
        "",
        "jaxrefl's raw predictions (unclipped):",
        "",
        table(headers, _error_rows(results, raw_order, None)),
        "",
        "Every model's predictions clamped to [0, 1], as a renderer displays them (the Adam "
        "peer's own output: its renderer clamps before anyone sees it):",
        "",
        table(headers, _error_rows(results, order, "clamped")),
    ]
    if "adam" in results:
        a = results["adam"]
        text += [
            "",
            f"adam's raw linear radiance, which its renderer never shows: mean "
            f"{_fmt(float(np.nanmean(a['per_photo'])))}, per photo "
            + ", ".join(_fmt(v) for v in a["per_photo"])
            + f"; p50 px {_fmt(a['p50'])}, p99 px {_fmt(a['p99'])}",
        ]
    gaps = [results[m]["refit_raw_gap"] for m in raw_order if "refit_raw_gap" in results[m]]
    if gaps:
        text += [
            "",
            "the clamped figures come from a second pass over the same folds (the CPU seconds'); "
            f"its raw RMSE per photo matches the table's within {max(gaps):.1e}",
        ]
    text += [
        "",
        table(
            [
                "model",
                "run s (all folds)",
                "compile s",
                "CPU s",
                "AT_BOUND share",
                "NOT_IDENTIFIED share",
                "Laplace-reliable share",
            ],
            t_rows,
        ),
    ]
    if "pooled" in results and results["pooled"].get("pooled"):
        ch = results["pooled"]["pooled"]
        alphas = [c["alpha"] for c in ch]
        models_ch = sorted({c["model"] for c in ch})
        fin = [a for a in alphas if a is not None]
        text += [
            "",
            f"pooled chose {', '.join(models_ch)} in the {len(ch)} folds"
            + (f"; shared alpha {min(fin):.3f}-{max(fin):.3f}" if fin else ""),
        ]
    if "auto" in results and results["auto"].get("auto"):
        ch = [c["model"] for c in results["auto"]["auto"]]
        text += [
            "",
            "auto chose "
            + ", ".join(f"{m} in {ch.count(m)} of {len(ch)} folds" for m in sorted(set(ch))),
        ]
    return "\n".join(text), results


def _targets(name: str, results: dict) -> str:
    """The issue's targets for the default model (``auto``; ``pooled`` when auto was not
    run), checked against this run: against Lambert on raw predictions, against the Adam
    peer on predictions clamped to [0, 1] on both sides (the peer's own output)."""
    tag = "auto" if "auto" in results else "pooled"
    if not {"lambert", tag} <= set(results):
        return ""
    lam, new = results["lambert"], results[tag]
    lines = []
    m_new, m_lam = float(np.nanmean(new["per_photo"])), float(np.nanmean(lam["per_photo"]))
    lines.append(f"mean / Lambert, raw {m_new / m_lam:.2f} (target <= 0.70)")
    if "adam" in results:
        m_adam = float(np.nanmean(results["adam"]["clamped"]["per_photo"]))
        m_clamp = float(np.nanmean(new["clamped"]["per_photo"]))
        lines.append(f"mean / Adam, both clamped to [0, 1] {m_clamp / m_adam:.2f} (target <= 0.80)")
        if new.get("cpu_s") and results["adam"].get("cpu_s"):
            lines.append(
                f"Adam CPU s / {tag} CPU s {results['adam']['cpu_s'] / new['cpu_s']:.1f} "
                "(target >= 10)"
            )
    worse = [int(i) for i in np.flatnonzero(new["per_photo"] > lam["per_photo"])]
    lines.append(f"photos worse than Lambert, raw: {worse or 'none'}")
    lines.append(f"p99 per pixel, raw {new['p99']:.4f} against Lambert's {lam['p99']:.4f}")
    return f"{name} ({tag}): " + "; ".join(lines)


CAPTURES = "bath_tile,yellow_box"
# The light column's rows: the stated flash, each estimate forced in every fold, and auto
# (an estimate kept only where the fold's own training photos support it).
LIGHT_ROWS = ("fixed", "offset", "offset+gains", "auto")


# The per-photo noise of a light's ratio to fixed: a paired spatial block bootstrap of the
# held-out squared errors over BLOCK x BLOCK pixel blocks (neighbouring pixels' errors are
# correlated: a misplaced highlight spans many), BOOT resamples, a fixed seed.
BLOCK = 16
BOOT = 2000
RATIO_Z = 2.0  # a photo counts as worse (better) where its ratio exceeds 1 by this many SE


def _heldout_errors(cap, fit, i: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) squared error of photo ``i``'s held-out prediction summed over channels, and
    the count of its uncensored valid observations, under the fit's light (a held-out
    photo at its prior gain)."""
    from jaxrefl.svbrdf import predict_photos

    pred = predict_photos(fit, cap, [i])[1][0]
    use = (cap.status[i] == 0) & np.isfinite(pred)
    e = np.where(use, pred - cap.images[i], 0.0)
    return np.sum(e * e, axis=-1), np.sum(use, axis=-1).astype(np.float64)


def _block_sums(a: np.ndarray) -> np.ndarray:
    """(B,) sums of ``a`` (H, W) over BLOCK x BLOCK blocks (the edge's partial blocks too)."""
    h, w = a.shape
    hb, wb = -(-h // BLOCK), -(-w // BLOCK)
    pad = np.zeros((hb * BLOCK, wb * BLOCK))
    pad[:h, :w] = a
    return pad.reshape(hb, BLOCK, wb, BLOCK).sum((1, 3)).ravel()


def _ratio_se(sse: np.ndarray, cnt: np.ndarray, sse_f: np.ndarray, cnt_f: np.ndarray) -> float:
    """The standard error of one photo's held-out RMSE ratio (a light / fixed) by the paired
    spatial block bootstrap: the same blocks resampled with replacement for both lights."""
    s, n, s_f, n_f = (_block_sums(a) for a in (sse, cnt, sse_f, cnt_f))
    rng = np.random.default_rng(0)
    picks = rng.integers(0, s.size, size=(BOOT, s.size))
    w = np.stack([np.bincount(p, minlength=s.size) for p in picks]).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.sqrt((w @ s) / (w @ n)) / np.sqrt((w @ s_f) / (w @ n_f))
    return float(np.nanstd(ratio, ddof=1))


def _light_fold_loo(cap, model: str, light: str) -> tuple[np.ndarray, list[dict], dict]:
    """Held-out RMSE per photo of ``model`` with the flash ``light``, each fold's light, and
    the held-out squared errors and counts (K, H, W) with the largest gap between their
    RMSE and the fit's report (``gap``)."""
    from jaxrefl.svbrdf import FitJob, fit_capture

    k, h, w, _c = cap.shape
    per = np.full(k, np.nan)
    lights = []
    errs = {"sse": np.zeros((k, h, w)), "cnt": np.zeros((k, h, w)), "gap": 0.0}
    for i in range(k):
        t0 = time.perf_counter()
        fit = fit_capture(cap, FitJob(model=model, holdout=(i,), light=light))
        v = fit.report["heldout_rmse_per_photo"][str(i)]
        per[i] = np.nan if v is None else v
        errs["sse"][i], errs["cnt"][i] = _heldout_errors(cap, fit, i)
        mine = np.sqrt(errs["sse"][i].sum() / max(errs["cnt"][i].sum(), 1.0))
        errs["gap"] = max(errs["gap"], abs(mine - per[i]))
        lt = fit.report["light"]
        lights.append(lt)
        off = "" if lt["offset_std_cm"] is None else f", offset {_offset(lt)} cm"
        print(
            f"    {light}: photo {i} held out, RMSE {per[i]:.5f}, kept {lt['mode']}{off} "
            f"({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    return per, lights, errs


def _offset(lt: dict) -> str:
    """A fold's estimated offset in the sample plane, x and y with their reported std."""
    o, sd = lt["offset_cm"], lt["offset_std_cm"]
    return f"({o[0]:+.2f} +- {sd[0]:.2f}, {o[1]:+.2f} +- {sd[1]:.2f})"


def _spread(lts: list[dict]) -> str:
    """The folds' offsets against their stds: the jackknife standard error of the offset
    over the folds (each fold leaves one photo out), beside the folds' mean reported std
    and mean Laplace std (x and y, cm)."""
    o = np.asarray([lt["offset_cm"][:2] for lt in lts])
    g = o.shape[0]
    jack = np.sqrt((g - 1) / g * np.sum((o - o.mean(0)) ** 2, 0))
    rep = np.mean([lt["offset_std_cm"][:2] for lt in lts], 0)
    lap = np.mean([lt["offset_std_cm_laplace"][:2] for lt in lts], 0)
    return (
        f"jackknife SE over the folds ({jack[0]:.3f}, {jack[1]:.3f}), mean reported std "
        f"({rep[0]:.3f}, {rep[1]:.3f}), mean Laplace std ({lap[0]:.3f}, {lap[1]:.3f})"
    )


def light_column(name: str, size: int, model: str, modes: tuple[str, ...] = LIGHT_ROWS) -> str:
    """The light column's table for capture ``name`` (module docstring): the rows ``modes``
    (``fixed`` always, the reference)."""
    modes = ("fixed", *[m for m in modes if m != "fixed"])
    cap = flash_capture(name, size)
    k = cap.n_photos
    per: dict[str, np.ndarray] = {}
    lights: dict[str, list[dict]] = {}
    errs: dict[str, dict] = {}
    secs: dict[str, float] = {}
    for mode in modes:
        t0 = time.perf_counter()
        per[mode], lights[mode], errs[mode] = _light_fold_loo(cap, model, mode)
        secs[mode] = time.perf_counter() - t0
    fixed = per["fixed"]
    label = {
        "fixed": "fixed",
        "offset": "offset (forced)",
        "offset+gains": "offset+gains (forced)",
        "auto": "auto",
    }
    headers = ["light", *[f"photo {i}" for i in range(k)], "mean", "s (all folds)"]
    rows = [
        [label[m], *[_fmt(v) for v in per[m]], _fmt(float(np.nanmean(per[m]))), f"{secs[m]:.0f}"]
        for m in modes
    ]
    notes = []
    ef = errs["fixed"]
    for m in modes[1:]:
        ratio = per[m] / fixed
        em = errs[m]
        boot = np.array(
            [_ratio_se(em["sse"][i], em["cnt"][i], ef["sse"][i], ef["cnt"][i]) for i in range(k)]
        )
        rows.append(
            [
                f"{label[m]} / fixed",
                *[_fmt(v, 3) for v in ratio],
                _fmt(float(np.nanmean(per[m])) / float(np.nanmean(fixed)), 3),
                "",
            ]
        )
        rows.append([f"{label[m]} / fixed, block SE", *[_fmt(v, 3) for v in boot], "", ""])
        z = (ratio - 1.0) / boot
        worse = [int(i) for i in np.flatnonzero(z > RATIO_Z)]
        better = [int(i) for i in np.flatnonzero(z < -RATIO_Z)]
        # The noise of the mean ratio: the photos' spread (each photo is one replicate).
        se = float(np.nanstd(ratio, ddof=1) / np.sqrt(np.sum(np.isfinite(ratio))))
        notes.append(
            f"{label[m]} / fixed per photo {np.nanmin(ratio):.3f} to {np.nanmax(ratio):.3f}, "
            f"mean {np.nanmean(ratio):.3f} +- {se:.3f} (standard error over photos); photos "
            f"worse by more than {RATIO_Z:g} block SE: {worse or 'none'}, better by more "
            f"than {RATIO_Z:g}: {better or 'none'}"
        )
    gap = max(e["gap"] for e in errs.values())
    text = [
        f"**{name}**, {size} x {size}, {k} photos, model `{model}`, each photo held out in "
        "turn (held-out RMSE, linear radiance):",
        "",
        table(headers, rows),
        "",
        f"block SE: the standard error of a photo's ratio by a paired spatial block "
        f"bootstrap ({BOOT} resamples of the photo's {BLOCK} x {BLOCK}-pixel blocks with "
        "replacement, the same blocks for both lights, the ratio of the resampled held-out "
        "RMSEs): the noise of which surface patches the photo shows, given the folds' fits "
        "(not the spread of the fits themselves). The squared errors are recomputed from each "
        f"fold's predictions; their RMSE matches the table's within {gap:.1e}.",
        "",
    ]
    if "auto" in lights:
        kept = [lt["mode"] for lt in lights["auto"]]
        counts = [f"{m} in {kept.count(m)} of {k} folds" for m in sorted(set(kept))]
        text.append("auto kept " + ", ".join(counts))
    for note in notes:
        text.append(f"; {note}")
    for m in [m for m in ("offset", "offset+gains") if m in lights]:
        text.append(
            f"; {label[m]}'s offset (cm, x and y, reported std: {lights[m][0]['covariance']}) "
            "per fold: " + ", ".join(_offset(lt) for lt in lights[m]) + f"; {_spread(lights[m])}"
        )
    if "auto" in lights:
        est = [lt for lt in lights["auto"] if lt["mode"] != "fixed"]
        if est:
            text.append("; auto's offset (cm) where kept: " + ", ".join(_offset(lt) for lt in est))
        checked = [lt for lt in lights["auto"] if lt.get("model_cv_rmse")]
        vetoed = [lt for lt in checked if lt["mode"] == "fixed"]
        text.append(
            f"; {model} checked auto's estimate in {len(checked)} of {k} folds and sent it back "
            f"to fixed in {len(vetoed)}"
        )
        text.append(f"; first fold's why: {lights['auto'][0]['why']}")
    # the title, the table and its legend as lines; the notes as one paragraph
    return "\n".join(text[:6]) + "\n" + " ".join(text[6:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--captures", default=CAPTURES)
    ap.add_argument("--models", default="lambert,ggx,pooled,auto,adam")
    ap.add_argument("--adam-steps", type=int, default=1000)
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument(
        "--light-only",
        action="store_true",
        help="run only the light column: held-out RMSE per photo, light estimated vs fixed",
    )
    ap.add_argument("--light-model", default="pooled", help="the model of the light column")
    ap.add_argument(
        "--light-rows",
        default=",".join(LIGHT_ROWS),
        help="the light column's rows (fixed always): of " + ", ".join(LIGHT_ROWS),
    )
    args = ap.parse_args(argv)
    if args.light_only:
        rows = tuple(args.light_rows.split(","))
        bad = [r for r in rows if r not in LIGHT_ROWS]
        if bad:
            ap.error(f"--light-rows: {', '.join(bad)} not among {', '.join(LIGHT_ROWS)}")
        date = datetime.date.today().isoformat()
        parts = [
            "## Real flash captures, the flash estimated or fixed (`benchmarks/real_captures.py "
            "--light-only`)",
            "",
            f"{date}; {machine()}; `--light-only --size {args.size} --light-model "
            f"{args.light_model}"
            + ("" if args.captures == CAPTURES else f" --captures {args.captures}")
            + ("" if rows == LIGHT_ROWS else f" --light-rows {args.light_rows}")
            + "`.",
        ]
        for name in args.captures.split(","):
            text = light_column(name, args.size, args.light_model, rows)
            print(text, flush=True)
            parts += ["", text]
            if not args.no_write:
                print(f"wrote {write_section('real_captures_light', chr(10).join(parts))}")
        return 0
    models = args.models.split(",")
    date = datetime.date.today().isoformat()
    parts = [
        "## Real flash captures, leave-one-photo-out (`benchmarks/real_captures.py`)",
        "",
        f"{date}; {machine()}; `--size {args.size} --models {args.models} "
        f"--adam-steps {args.adam_steps}`.",
    ]
    summary = []
    for name in args.captures.split(","):
        text, results = run_capture(name, args.size, models, args.adam_steps)
        print(text, flush=True)
        parts += ["", text]
        summary.append(_targets(name, results))
    summary = [s for s in summary if s]
    if summary:
        parts += [
            "",
            "Targets (the default model against Lambert, raw, and against the Adam peer, both "
            "clamped to [0, 1]):",
            "",
        ]
        parts += [f"- {s}" for s in summary]
        print("\n".join(summary))
    if not args.no_write:
        print(f"wrote {write_section('real_captures', chr(10).join(parts))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
