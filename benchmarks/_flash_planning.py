"""Capture planning for a flash capture (``jaxrefl.svbrdf.plan_next``): the part of
``benchmarks/capture_planning.py`` run with ``--flash``.

    python benchmarks/capture_planning.py --flash [--size 64] [--subsets 40] [--model pooled]
        [--family-size 32] [--budget 12] [--target 0.1]

Real photos (``bath_tile``, ``yellow_box``, 9 photos each, read at ``--size``): for random
subsets of 5 photos, fit ``--model`` on the 5, rank the other 4 by the plan (their camera
and flash positions as candidates; each criterion of :class:`jaxrefl.svbrdf.PlanOptions`),
then for each of the 4 fit on the 5 plus it and score the held-out RMSE (linear radiance)
on the 3 left. Per capture and criterion: the plan's pick's RMSE, the random pick's (the
mean over the 4), the oracle's (the best of the 4), the share of the random-to-oracle gap
the plan closes, and how often the plan picks the oracle's photo; a row ``worst
predicted`` picks the photo the 5-photo fit predicts worst (not a plan: it needs the
photos), the part of the oracle's lead that comes from the pick leaving the scored photos.
A second table scores every pick on the same held-out photo (each of the 4 in turn, the
pick the best-ranked of the other 3), from the same fits. Every fit is of the full 9-photo
capture with the photos not in use held out (weight 0), so one compiled fit serves all.

Generated captures (``benchmarks/capture_family.py``: the members' true maps, rendered at
``--family-size`` from any camera position by :func:`render_at`, the flash at its true
offset and the capture told so): from the same 3 start photos (the member's own first
three), add photos one at a time by the plan (the best of a hemisphere grid at 24 cm,
:func:`jaxrefl.svbrdf.hemisphere_candidates`, after a refit; the default criterion, and
``information``), at random from the same grid
(3 orders), or in a fixed 3 x 3 pattern (a square grid 6 cm apart, 24 cm up, centre
first); fit the per-pixel ``ggx`` model; photos until the median |ln alpha error| over the
pixels is at most ``--target`` and half of it (``>budget`` where it is not reached within
``--budget`` photos), the error at the budget, and the ratio of photos needed (random or
3 x 3 over the plan's).
"""

from __future__ import annotations

import argparse
import time

import jax.numpy as jnp
import numpy as np
from _common import machine, shared_data, table
from capture_family import FAMILY, NOISE_FLOOR, _maps, _rig

from jaxrefl import svbrdf
from jaxrefl.io import Capture, ObsStatus, load_capture

REAL = ("bath_tile", "yellow_box")
FAMILY_MEMBERS = ("colocated_tiles", "grey_gloss")


# ----------------------------------------------------------------------------- real photos
CRITERIA = ("variance", "information")
# Not a plan: the photo the fit predicts worst (needs the photos).
WORST = "worst predicted"


def _gap_row(label, crit, plan, rand, orc, hits, n, chance, extra):
    p, r, o = np.mean(plan), np.mean(rand), np.mean(orc)
    wins = np.mean(np.asarray(plan) < np.asarray(rand))
    return [
        label,
        crit,
        f"{p:.5f}",
        f"{r:.5f}",
        f"{o:.5f}",
        f"{(r - p) / (r - o):.2f}" if r > o else "-",
        f"{hits}/{n} ({hits / n:.0%}; chance {chance})",
        f"{wins:.0%}",
        *extra,
    ]


def real_part(args, rng) -> None:
    print("## Real captures: pick the 6th photo of 5\n")
    print(
        f"{args.subsets} random subsets of 5 of the 9 photos per capture, {args.size} x "
        f"{args.size} pixels, model `{args.model}`; held-out RMSE (linear radiance) on the 3 "
        "photos left after adding the pick. Criterion: `variance` (the default: expected "
        "reduction of the predictive variance of renderings at the 4 candidates) and "
        "`information` (expected information gain about the parameters).\n"
    )
    rows, fixed_rows = [], []
    for name in REAL:
        t0 = time.perf_counter()
        cap = load_capture(shared_data() / "svbrdf_flash" / name)
        cap = cap.downsample(cap.shape[1] // args.size)
        k = cap.n_photos
        subsets = set()
        while len(subsets) < args.subsets:
            subsets.add(tuple(sorted(rng.choice(k, 5, replace=False).tolist())))
        ranks: dict[str, list[list[int]]] = {c: [] for c in (*CRITERIA, WORST)}
        errs, per_photo = [], []
        for s in sorted(subsets):
            others = [i for i in range(k) if i not in s]
            job = svbrdf.FitJob(model=args.model, holdout=tuple(others))
            base = svbrdf.fit_capture(cap, job)
            for crit in CRITERIA:
                plan = svbrdf.plan_next(
                    base,
                    cap,
                    svbrdf.photo_candidates(cap, others),
                    svbrdf.PlanOptions(criterion=crit),
                )
                ranks[crit].append([others[m] for m in plan.order])
            b = {int(j): v for j, v in base.report["heldout_rmse_per_photo"].items()}
            ranks[WORST].append(sorted(b, key=lambda j: -b[j]))
            err, pp = {}, {}
            for o in others:
                rest = tuple(i for i in others if i != o)
                r = svbrdf.fit_capture(cap, svbrdf.FitJob(model=args.model, holdout=rest))
                err[o] = r.report["heldout_rmse"]
                pp[o] = {int(j): v for j, v in r.report["heldout_rmse_per_photo"].items()}
            errs.append(err)
            per_photo.append(pp)
        secs = f"{time.perf_counter() - t0:.0f}"
        n = len(errs)
        rand = [float(np.mean(list(e.values()))) for e in errs]
        orc = [min(e.values()) for e in errs]
        best = [min(e, key=lambda i: e[i]) for e in errs]
        for crit, rk in ranks.items():
            chosen = [r[0] for r in rk]
            plan_err = [e[c] for e, c in zip(errs, chosen, strict=True)]
            hits = sum(c == b for c, b in zip(chosen, best, strict=True))
            rows.append(_gap_row(name, crit, plan_err, rand, orc, hits, n, "25%", [secs]))
            # The same held-out photo for every pick: each of the 4 in turn, the pick the
            # best-ranked of the other 3.
            fp, fr, fo, fh = [], [], [], 0
            for e, pp, r in zip(errs, per_photo, rk, strict=True):
                for h in e:
                    score = {c: pp[c][h] for c in e if c != h}
                    pick = next(c for c in r if c in score)
                    fp.append(score[pick])
                    fr.append(float(np.mean(list(score.values()))))
                    fo.append(min(score.values()))
                    fh += pick == min(score, key=lambda c: score[c])
            fixed_rows.append(_gap_row(name, crit, fp, fr, fo, fh, len(fp), "33%", []))
    head = [
        "capture",
        "criterion",
        "plan's pick",
        "random pick",
        "oracle",
        "gap closed",
        "plan picks the oracle's photo",
        "plan below random",
    ]
    print(table([*head, "s"], rows))
    print(
        "\nrandom pick: the mean over the 4; oracle: the best of the 4. gap closed: (random - "
        "plan) / (random - oracle), 1 = the oracle, 0 = no better than a random pick, "
        "negative = worse. plan below random: share of subsets where the plan's pick "
        "predicts the 3 left better than the mean of the 4. `worst predicted` is no plan: it "
        "picks the photo the 5-photo fit predicts worst, which needs the photos themselves; "
        "the pick leaves the scored photos, so a photo the model predicts badly (for reasons "
        "the fit does not see) lowers the score by leaving them.\n"
    )
    print("### Real captures: the same held-out photo for every pick\n")
    print(
        "Each of the 4 photos in turn is the held-out one; the pick is among the other 3 "
        "(the plan's ranking of the 4 without it); held-out RMSE on that one photo. This "
        "scores what a pick teaches the fit without the pick leaving the scored photos.\n"
    )
    print(table(head, fixed_rows))
    print()


# ----------------------------------------------------------------------------- generated
def render_at(member, truth, cams, lights, rng) -> Capture:
    """A capture of ``member``'s true maps from cameras ``cams`` with flashes at ``lights``
    ((K, 3) cm), rendered and noised as :func:`capture_family.render_member` does (ggx_rgb,
    no vignetting, noise ``member.noise``, clipped to [0, 1], 1 marked saturated); the
    capture is told the true flash positions."""
    from jaxrefl.scene import PinholeCamera, PointLight, planar_points, render

    m = member
    model, _space = svbrdf.capture_model("ggx_rgb")
    params = {n: jnp.asarray(truth[n]) for n in model.param_names}
    power = np.full((len(cams), 3), m.light_power)
    points = planar_points(m.size, m.size, m.side_cm)
    radiance = np.asarray(
        render(
            model,
            params,
            [PointLight(p, e) for p, e in zip(lights, power, strict=True)],
            [PinholeCamera(p) for p in cams],
            points=points,
            cos4=False,
        ),
        np.float64,
    )
    std = m.noise * (radiance + NOISE_FLOOR)
    images = np.clip(radiance + std * rng.standard_normal(radiance.shape), 0.0, 1.0)
    status = np.where(images >= 1.0, ObsStatus.SATURATED, ObsStatus.OK).astype(np.uint8)
    return Capture(
        images=images.astype(np.float32),
        status=status,
        light_pos=np.asarray(lights, np.float64),
        light_dir=None,
        light_power=power,
        camera_pos=np.asarray(cams, np.float64),
        side=m.side_cm,
        points=np.asarray(points, np.float64),
        saturation_level=1.0,
    )


def _alpha_error(result, truth) -> float:
    a = np.asarray(result.maps["alpha"], np.float64)
    err = np.abs(np.log(a) - np.log(truth["alpha"]))
    return float(np.median(np.where(np.isfinite(err), err, np.inf)))


def _sequence(member, truth, offset, start, pick, budget, seed):
    """Median |ln alpha error| after 3 ... ``budget`` photos; ``pick(fit, capture, taken)``
    gives the next camera position. Slots not yet taken are held out (one compiled fit)."""
    cams = np.array(list(start) + [start[0]] * (budget - len(start)), np.float64)
    errors = []
    for n in range(len(start), budget + 1):
        cap = render_at(member, truth, cams, cams + offset, np.random.default_rng(seed))
        job = svbrdf.FitJob(model="ggx", holdout=tuple(range(n, budget)))
        result = svbrdf.fit_capture(cap, job)
        errors.append(_alpha_error(result, truth))
        if n < budget:
            cams[n] = pick(result, cap, n)
    return errors


def _needed(errors, start: int, target: float, budget: int) -> str:
    for n, e in enumerate(errors, start=start):
        if e <= target:
            return str(n)
    return f">{budget}"


def generated_part(args, rng) -> None:
    import dataclasses

    print("## Generated captures: photos until the maps are accurate\n")
    print(
        f"{args.family_size} x {args.family_size} pixels, per-pixel `ggx`, 3 start photos, "
        f"budget {args.budget} photos; target: median |ln alpha error| <= {args.target} "
        f"(and <= {args.target / 2:g}). "
        "Photos needed (start included) and the error at the budget.\n"
    )
    rows = []
    keys = ("plan", "plan (information)", "random", "3x3")
    counts: dict[float, dict[str, list[float]]] = {
        t: {key: [] for key in keys} for t in (args.target, args.target / 2)
    }
    for name in FAMILY_MEMBERS:
        t0 = time.perf_counter()
        m = dataclasses.replace(next(f for f in FAMILY if f.name == name), size=args.family_size)
        r0 = np.random.default_rng(m.seed)
        truth = _maps(m, r0)
        cams, lights = _rig(m, r0)
        offset = lights[0] - cams[0]
        start = cams[:3]
        grid = None

        def plan_pick(result, cap, n, criterion="variance"):
            nonlocal grid
            taken = cap.select(list(range(n)))
            if grid is None:
                grid = svbrdf.hemisphere_candidates(taken)
            options = svbrdf.PlanOptions(criterion=criterion)
            plan = svbrdf.plan_next(result, cap, grid, options)
            return grid.camera_pos[plan.best]

        seq = {"plan": _sequence(m, truth, offset, start, plan_pick, args.budget, 1)}
        seq["plan (information)"] = _sequence(
            m,
            truth,
            offset,
            start,
            lambda res, cap, n: plan_pick(res, cap, n, "information"),
            args.budget,
            1,
        )
        grid_pos = svbrdf.hemisphere_candidates(render_at(m, truth, start, start + offset, r0))
        rand = []
        for s in range(3):
            order = np.random.default_rng(100 + s).permutation(len(grid_pos))
            rand.append(
                _sequence(
                    m,
                    truth,
                    offset,
                    start,
                    lambda res, cap, n, o=order, g=grid_pos: g.camera_pos[o[n - 3]],
                    args.budget,
                    1,
                )
            )
        xy = [(0, 0), (6, 0), (0, 6), (-6, 0), (0, -6), (6, 6), (-6, 6), (-6, -6), (6, -6)]
        pattern = np.array([[x, y, 24.0] for x, y in xy])
        seq["3x3"] = _sequence(
            m, truth, offset, start, lambda res, cap, n, p=pattern: p[(n - 3) % 9], args.budget, 1
        )
        for t, cnt in counts.items():
            for key in ("plan", "plan (information)", "3x3"):
                nd = _needed(seq[key], 3, t, args.budget)
                cnt[key].append(float(nd) if not nd.startswith(">") else np.inf)
            need = [_needed(e, 3, t, args.budget) for e in rand]
            cnt["random"].append(
                float(np.mean([float(n) if not n.startswith(">") else np.inf for n in need]))
            )
        need_rand = [_needed(e, 3, args.target, args.budget) for e in rand]
        strict = args.target / 2
        need_rand2 = [_needed(e, 3, strict, args.budget) for e in rand]
        rows.append(
            [
                name,
                _needed(seq["plan"], 3, args.target, args.budget),
                _needed(seq["plan (information)"], 3, args.target, args.budget),
                ", ".join(need_rand),
                _needed(seq["3x3"], 3, args.target, args.budget),
                _needed(seq["plan"], 3, strict, args.budget),
                _needed(seq["plan (information)"], 3, strict, args.budget),
                ", ".join(need_rand2),
                _needed(seq["3x3"], 3, strict, args.budget),
                f"{seq['plan'][-1]:.3f}",
                f"{seq['plan (information)'][-1]:.3f}",
                f"{np.mean([e[-1] for e in rand]):.3f}",
                f"{seq['3x3'][-1]:.3f}",
                f"{time.perf_counter() - t0:.0f}",
            ]
        )
        print(
            f"{name}: median |ln alpha error| by photo count 3..{args.budget}: plan "
            + " ".join(f"{e:.3f}" for e in seq["plan"])
            + "; plan (information) "
            + " ".join(f"{e:.3f}" for e in seq["plan (information)"])
            + "; random (mean of 3) "
            + " ".join(f"{e:.3f}" for e in np.mean(rand, axis=0))
            + "; 3x3 "
            + " ".join(f"{e:.3f}" for e in seq["3x3"])
        )
    print()
    print(
        table(
            [
                "member",
                "plan",
                "plan (information)",
                "random (3 orders)",
                "3 x 3 pattern",
                f"plan (<= {args.target / 2:g})",
                "plan (information)",
                "random",
                "3 x 3",
                f"plan error at {args.budget}",
                "plan (information) error",
                "random error",
                "3 x 3 error",
                "s",
            ],
            rows,
        )
    )
    print(
        "\nphotos needed, ratio to the plan's (the mean over members where both reach the "
        "target; random: the mean of its 3 orders, where all 3 reach it):"
    )
    for t, cnt in counts.items():
        parts = []
        for plan_key in ("plan", "plan (information)"):
            for key in ("random", "3x3"):
                both = [
                    (b, a)
                    for a, b in zip(cnt[plan_key], cnt[key], strict=True)
                    if np.isfinite(a) and np.isfinite(b)
                ]
                r = f"{np.mean([b / a for b, a in both]):.2f}" if both else "- (not reached)"
                parts.append(f"{key} / {plan_key} {r} ({len(both)} of {len(cnt[key])})")
        print(f"- median |ln alpha error| <= {t:g}: " + ", ".join(parts))


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--flash", action="store_true", help="this part")
    ap.add_argument("--size", type=int, default=64, help="real captures' pixels a side")
    ap.add_argument("--subsets", type=int, default=40, help="random 5-photo subsets a capture")
    ap.add_argument("--model", default="pooled", help="capture model of the real part")
    ap.add_argument("--family-size", type=int, default=32, help="generated captures' size")
    ap.add_argument("--budget", type=int, default=12, help="photos at most (generated)")
    ap.add_argument("--target", type=float, default=0.1, help="median |ln alpha error|")
    ap.add_argument("--skip-real", action="store_true", help="only the generated part")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    print(f"machine: {machine()}\n")
    if not args.skip_real:
        real_part(args, rng)
    generated_part(args, rng)
    print(f"\n({time.perf_counter() - t0:.0f} s)")
    return 0
