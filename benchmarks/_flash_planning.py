"""Capture planning for a flash capture (``jaxrefl.svbrdf.plan_next``): the part of
``benchmarks/capture_planning.py`` run with ``--flash``.

    python benchmarks/capture_planning.py --flash [--size 64] [--subsets 40] [--model pooled]
        [--family-size 32] [--budget 12] [--target 0.1] [--ref-share 0.5] [--fit-model ggx_rgb]
        [--members a,b] [--random-orders 3] [--skip-real | --keep-real] [--keep-generated]

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

Generated captures (``benchmarks/capture_family.py``, ``--members``, default
:data:`FAMILY_MEMBERS`: the flash at the lens, near-mirror lacquer, a grey gloss and a
coloured metal; the members' true maps, rendered at ``--family-size``
from any camera position by :func:`render_at`, the flash at its true offset and the capture
told so): from the same 3 start photos (the member's own first three), add photos one at a
time by the plan (the best of a hemisphere grid at 24 cm,
:func:`jaxrefl.svbrdf.hemisphere_candidates`, after a refit; each of ``--criteria``), at
random from the same grid (``--random-orders`` orders), or in a fixed 3 x 3 pattern (a
square grid 6 cm apart, 24 cm up, centre first). Each fit is ``--fit-model`` (default
``ggx_rgb``, the truth's family: ``ggx``'s grey F0 cannot render a coloured metal) on the
photos taken so far only, with the library's defaults otherwise, so the lower bound of alpha
is those photos' resolvable width (:func:`jaxrefl.svbrdf.resolvable_alpha`), as a user's
``jaxrefl fit --photos`` has it. Two targets: median |ln alpha error| over the pixels at most
``--target``, and the member's own: ``--ref-share`` of the way, in log error, from the
start's error to that of a fit on the start and every candidate of the grid (the reference,
what the candidates teach together whatever the order; 0.5: the geometric mean of the two).
It depends on no strategy (the start is common to all), and a member reaches it even where
its lobes are narrower than the photos resolve (``--target`` out of reach) or where the
reference, on over a hundred photos, is far beyond a few. Photos
needed per target (``>budget`` where not reached within ``--budget`` photos), the ratios
random / plan and 3 x 3 / plan per member and on average, the error at the budget.

``--keep-real`` prints the real part of the recorded section again, with the date and
arguments of the run that measured it, so that a rerun of the generated part alone keeps it;
``--keep-generated`` keeps the generated part alike.
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _common import machine, shared_data, table
from capture_family import FAMILY, NOISE_FLOOR, _maps, _rig

from jaxrefl import svbrdf
from jaxrefl.io import Capture, ObsStatus, load_capture
from jaxrefl.svbrdf import _plan

REAL = ("bath_tile", "yellow_box")
SECTION = "capture_planning_flash"  # this part's section of docs/benchmarks.md
KEPT = "Kept from the recorded run"  # how --keep-real / --keep-generated head a kept part
# What the generated part runs by default: members that differ in what users vary most
# (flash offset 0 to 1 cm, near-mirror to rough lobes, grey F0 up to 0.5, a coloured metal,
# noise 0.5% to 1%); the others of the family take --members.
FAMILY_MEMBERS = ("colocated_tiles", "mirror_plastic", "grey_gloss", "gold_foil")


# ----------------------------------------------------------------------------- real photos
CRITERIA = _plan.CRITERIA  # every criterion of PlanOptions, the default first
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
        "photos left after adding the pick. Criteria (jaxrefl.svbrdf.PlanOptions; the "
        f"default: `{svbrdf.PlanOptions().criterion}`): `variance` (expected reduction of the "
        "predictive variance of renderings at the 4 candidates, summed over pixels), "
        "`log_variance` (the same pixel by pixel: mean log ratio) and `information` (expected "
        "information gain about the parameters).\n"
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


def kept_real_part() -> None:
    """Print the real part of the recorded section (``docs/benchmarks.md``) again, headed by
    the date and arguments of the run that measured it (``--keep-real``: a rerun of the
    generated part alone keeps it)."""
    _kept_part("--keep-real", "### Real captures: pick", "### Generated captures")


def kept_generated_part() -> None:
    """Print the generated part of the recorded section again, headed alike
    (``--keep-generated``: a rerun of the real part alone keeps it)."""
    _kept_part("--keep-generated", "### Generated captures", None)


def _kept_part(flag: str, first: str, last: str | None) -> None:
    """The recorded section's part from the heading ``first`` to ``last`` (None: to the run's
    closing time), printed as the script prints it, under a line naming its run."""
    path = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
    text = path.read_text() if path.exists() else ""
    start, end = f"<!-- {SECTION}:start -->", f"<!-- {SECTION}:end -->"
    if start not in text:
        raise SystemExit(f"{flag}: no recorded {SECTION} section in {path}; run it whole")
    body = text.split(start, 1)[1].split(end, 1)[0]
    head = body.strip().splitlines()[2]  # "DATE; MACHINE; `ARGS`." under the heading
    if first not in body or (last is not None and last not in body):
        raise SystemExit(f"{flag}: the recorded {SECTION} section has no such part")
    part = first + body.split(first, 1)[1]
    if last is not None:
        part = part.split(last, 1)[0]
    lines = part.strip().splitlines()
    if last is None and lines[-1].startswith("(") and lines[-1].endswith(" s)"):
        lines = lines[:-1]  # the recorded run's total time, not this run's
    # run_and_record moves every heading one level down; undo it, it does so again.
    lines = [ln[1:] if ln.startswith("##") else ln for ln in lines]
    print(lines[0] + "\n")
    if not lines[2].startswith(KEPT):  # kept once already: its own line says from where
        date, _, rest = head.partition("; ")
        where, _, recorded = rest.partition("; `")
        print(f"{KEPT} of {date} (`{recorded.rstrip('.').rstrip('`')}`; {where}); not rerun.\n")
    print("\n".join(lines[1:]).strip() + "\n")


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


def _sequence(member, truth, offset, start, pick, *, budget, seed, model):
    """Median |ln alpha error| after 3 ... ``budget`` photos; ``pick(fit, capture, taken)``
    gives the next camera position. Each fit is of the photos taken so far only (as
    ``jaxrefl fit --photos`` fits), so the capture's resolvable width
    (:func:`jaxrefl.svbrdf.resolvable_alpha`, the lower bound of alpha) is theirs; every
    photo keeps its noise (one render of the ``budget`` slots per step, the same seed)."""
    cams = np.array(list(start) + [start[0]] * (budget - len(start)), np.float64)
    errors = []
    for n in range(len(start), budget + 1):
        full = render_at(member, truth, cams, cams + offset, np.random.default_rng(seed))
        cap = full.select(range(n))
        result = svbrdf.fit_capture(cap, svbrdf.FitJob(model=model))
        errors.append(_alpha_error(result, truth))
        if n < budget:
            cams[n] = pick(result, cap, n)
    FLOORS.append(svbrdf.resolvable_alpha(cap))
    return errors


# The lower bound of alpha (the photos' resolvable width) of each sequence's last fit.
FLOORS: list[float] = []


def _reference(member, truth, offset, start, grid, seed, model) -> tuple[float, int]:
    """The median |ln alpha error| of a fit on the start and every candidate of ``grid``
    (what the candidates can teach at most, whatever the order), and its photo count. The
    fit is told the flash (``light='fixed'``: where it was rendered): ``auto`` would check
    the light by refitting it once without each of the over a hundred photos."""
    cams = np.concatenate([start, grid.camera_pos])
    cap = render_at(member, truth, cams, cams + offset, np.random.default_rng(seed))
    FLOORS.append(svbrdf.resolvable_alpha(cap))
    job = svbrdf.FitJob(model=model, light="fixed")
    return _alpha_error(svbrdf.fit_capture(cap, job), truth), len(cams)


def _needed(errors, start: int, target: float, budget: int) -> str:
    for n, e in enumerate(errors, start=start):
        if e <= target:
            return str(n)
    return f">{budget}"


def _ratio(other: float, plan: float, budget: int) -> str:
    """Photos needed by ``other`` over the plan's: '>x' where only the plan reaches the
    target within the budget (``other`` needs more than ``budget``), '<=x' where only
    ``other`` does, '-' where neither does."""
    if np.isfinite(other) and np.isfinite(plan):
        return f"{other / plan:.2f}"
    if np.isfinite(plan):
        return f">{budget / plan:.2f}"
    if np.isfinite(other):
        return f"<={other / (budget + 1):.2f}"
    return "-"


def generated_part(args, rng) -> None:
    import dataclasses

    criteria = args.criteria.split(",")
    plans = [f"plan ({c})" for c in criteria]
    keys = (*plans, "random", "3x3")
    print("## Generated captures: photos until the maps are accurate\n")
    print(
        f"{args.family_size} x {args.family_size} pixels, 3 start photos, budget "
        f"{args.budget} photos. Every fit is `FitJob(model={args.fit_model!r})` on the photos "
        "taken so far only, as `jaxrefl fit --photos` fits (defaults otherwise: the flash "
        "estimated or kept as the capture states it, `light='auto'`; the lower bound of alpha "
        "the photos' resolvable width). `ggx_rgb` is the truth's own family (the members are "
        "rendered with it): what `auto` (`jaxrefl fit`'s default) can choose at best, "
        "without its choice among five models re-made at every photo count (five times the "
        "fits). Plans by criterion: "
        f"{', '.join(criteria)} (the default: {svbrdf.PlanOptions().criterion}); random: "
        f"{args.random_orders} orders of the same grid; 3 x 3: a square grid 6 cm apart, "
        "24 cm up, centre first. Two targets: the absolute one, median |ln alpha error| <= "
        f"{args.target}; and a member's own, {args.ref_share:g} of the way in log error from "
        "the start's error to the reference's (a fit on the start and every candidate of the "
        "grid, told the flash: what the candidates teach together, whatever the order): the "
        "start's error^"
        f"{1 - args.ref_share:g} x the reference's^{args.ref_share:g}. It depends on no "
        "strategy, and a member reaches it even where its lobes are narrower than the photos "
        "resolve or the reference, on over a hundred photos, is far beyond a few. Photos "
        "needed (start included).\n"
    )
    rows: dict[str, list[list[str]]] = {"abs": [], "rel": []}
    end_rows = []
    counts: dict[str, dict[str, list[float]]] = {t: {k: [] for k in keys} for t in rows}
    for name in args.members.split(","):
        # Compiled programs of the last member's fits are dropped (the lower bound of alpha,
        # a float of the model, differs with each set of photos): the process's compiled
        # code, and the memory maps it holds, stay at about one member's.
        jax.clear_caches()
        t0 = time.perf_counter()
        m = dataclasses.replace(next(f for f in FAMILY if f.name == name), size=args.family_size)
        r0 = np.random.default_rng(m.seed)
        truth = _maps(m, r0)
        cams, lights = _rig(m, r0)
        offset = lights[0] - cams[0]
        start = cams[:3]
        grid = svbrdf.hemisphere_candidates(render_at(m, truth, start, start + offset, r0))
        ref, n_ref = _reference(m, truth, offset, start, grid, 1, args.fit_model)

        def plan_pick(result, cap, n, criterion, g=grid):
            plan = svbrdf.plan_next(result, cap, g, svbrdf.PlanOptions(criterion=criterion))
            return g.camera_pos[plan.best]

        run = functools.partial(
            _sequence, m, truth, offset, start, budget=args.budget, seed=1, model=args.fit_model
        )

        seq = {
            key: run(lambda res, cap, n, c=c: plan_pick(res, cap, n, c))
            for key, c in zip(plans, criteria, strict=True)
        }
        rand = []
        for s in range(args.random_orders):
            order = np.random.default_rng(100 + s).permutation(len(grid))
            rand.append(run(lambda res, cap, n, o=order, g=grid: g.camera_pos[o[n - 3]]))
        xy = [(0, 0), (6, 0), (0, 6), (-6, 0), (0, -6), (6, 6), (-6, 6), (-6, -6), (6, -6)]
        pattern = np.array([[x, y, 24.0] for x, y in xy])
        seq["3x3"] = run(lambda res, cap, n, p=pattern: p[(n - 3) % 9])
        first = seq["3x3"][0]  # the start's error: every strategy's first fit
        rel = first ** (1 - args.ref_share) * ref**args.ref_share
        for t, target in {"abs": args.target, "rel": rel}.items():
            need = {k: _needed(seq[k], 3, target, args.budget) for k in (*plans, "3x3")}
            rand_need = [_needed(e, 3, target, args.budget) for e in rand]
            cnt = counts[t]
            for k in (*plans, "3x3"):
                cnt[k].append(_count(need[k]))
            cnt["random"].append(float(np.mean([_count(x) for x in rand_need])))
            rows[t].append(
                [
                    name,
                    f"{target:.3f}",
                    *[need[k] for k in plans],
                    ", ".join(rand_need),
                    need["3x3"],
                    *[_ratio(cnt["random"][-1], cnt[k][-1], args.budget) for k in plans],
                    *[_ratio(cnt["3x3"][-1], cnt[k][-1], args.budget) for k in plans],
                ]
            )
        # The error over photos 4 .. budget (after the start), the plan's as a share of
        # random's: below 1, the plan's maps are better on average along the way.
        mean_rand = np.mean([e[1:] for e in rand])
        end_rows.append(
            [
                name,
                f"{ref:.3f} ({n_ref})",
                *[f"{seq[k][-1]:.3f}" for k in plans],
                f"{np.mean([e[-1] for e in rand]):.3f}",
                f"{seq['3x3'][-1]:.3f}",
                *[f"{np.mean(seq[k][1:]) / mean_rand:.2f}" for k in plans],
                f"{time.perf_counter() - t0:.0f}",
            ]
        )
        curves = [f"{k} " + " ".join(f"{e:.3f}" for e in seq[k]) for k in plans]
        curves.append(
            f"random (mean of {len(rand)}) " + " ".join(f"{e:.3f}" for e in np.mean(rand, 0))
        )
        curves.append("3x3 " + " ".join(f"{e:.3f}" for e in seq["3x3"]))
        # Sequences in the order run: plans, random orders, 3 x 3; the reference's first.
        floors = FLOORS[-(len(plans) + len(rand) + 2) :]
        below = np.mean(truth["alpha"] < floors[-1])
        print(
            f"{name}: median |ln alpha error| by photo count 3..{args.budget}: "
            + "; ".join(curves)
            + f"; reference ({n_ref} photos) {ref:.3f}. Lower bound of alpha (the photos' "
            f"resolvable width) at {args.budget} photos: "
            + ", ".join(f"{k} {f:.3f}" for k, f in zip(plans, floors[1:], strict=False))
            + f", random {np.mean(floors[1 + len(plans) : -1]):.3f}, 3x3 {floors[-1]:.3f}, "
            f"reference {floors[0]:.3f}; the truth's alpha: median "
            f"{np.median(truth['alpha']):.3f}, {below:.0%} of the pixels below 3x3's bound\n"
        )
    print()
    head = [
        "member",
        "target",
        *plans,
        f"random ({args.random_orders} orders)",
        "3 x 3",
        *[f"random / {k}" for k in plans],
        *[f"3 x 3 / {k}" for k in plans],
    ]
    labels = {
        "abs": f"median |ln alpha error| <= {args.target:g}",
        "rel": f"the member's own ({args.ref_share:g} of the way from the start's error to "
        "the reference's, in log)",
    }
    for t, label in labels.items():
        print(f"### Photos needed: {label}\n")
        print(table(head, rows[t]))
        print()
    print("### Error at the budget\n")
    print(
        table(
            [
                "member",
                "reference (photos)",
                *[f"{k} at {args.budget}" for k in plans],
                "random",
                "3 x 3",
                *[f"{k} / random, mean error" for k in plans],
                "s",
            ],
            end_rows,
        )
    )
    print(
        f"\nphotos needed: '>{args.budget}' where the target is not reached within the "
        f"budget; random: each order's, its column of ratios the mean of the "
        f"{args.random_orders} orders' counts (where all reach it). Ratios: photos needed by "
        "random or 3 x 3 over the plan's; '>x' where only the plan reaches the target (x "
        "counts the other's as the budget), '<=x' where only the other does (x counts the "
        "plan's as one over the budget). mean error: the median |ln alpha error| averaged "
        "over photos 4 .. budget, the plan's over random's (below 1: the plan's maps are "
        "better along the way). Mean ratios over the members where both reach the target:"
    )
    for t, label in labels.items():
        parts = []
        for plan_key in plans:
            for key in ("random", "3x3"):
                cnt = counts[t]
                both = [
                    (b, a)
                    for a, b in zip(cnt[plan_key], cnt[key], strict=True)
                    if np.isfinite(a) and np.isfinite(b)
                ]
                r = f"{np.mean([b / a for b, a in both]):.2f}" if both else "- (not reached)"
                parts.append(f"{key} / {plan_key} {r} ({len(both)} of {len(cnt[key])})")
        print(f"- {label}: " + ", ".join(parts))


def _count(needed: str) -> float:
    """Photos needed as a number, inf where the target was not reached."""
    return np.inf if needed.startswith(">") else float(needed)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--flash", action="store_true", help="this part")
    ap.add_argument("--size", type=int, default=64, help="real captures' pixels a side")
    ap.add_argument("--subsets", type=int, default=40, help="random 5-photo subsets a capture")
    ap.add_argument("--model", default="pooled", help="capture model of the real part")
    ap.add_argument("--family-size", type=int, default=32, help="generated captures' size")
    ap.add_argument("--budget", type=int, default=12, help="photos at most (generated)")
    ap.add_argument("--target", type=float, default=0.1, help="median |ln alpha error|")
    ap.add_argument(
        "--ref-share", type=float, default=0.5, help="own target: share of the way, start to ref"
    )
    ap.add_argument("--fit-model", default="ggx_rgb", help="capture model of the generated part")
    ap.add_argument("--skip-real", action="store_true", help="only the generated part")
    ap.add_argument("--keep-real", action="store_true", help="the recorded real part, not rerun")
    ap.add_argument(
        "--keep-generated", action="store_true", help="the recorded generated part, not rerun"
    )
    ap.add_argument("--members", default=",".join(FAMILY_MEMBERS), help="generated members")
    ap.add_argument("--random-orders", type=int, default=3, help="random orders a member")
    ap.add_argument(
        "--criteria",
        default=",".join(dict.fromkeys([svbrdf.PlanOptions().criterion, "information"])),
        help="plan criteria of the generated part (the default's first)",
    )
    args = ap.parse_args(argv)
    if not 0 < args.ref_share <= 1:
        ap.error(f"--ref-share must be in (0, 1], got {args.ref_share}")
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    print(f"machine: {machine()}\n")
    if args.keep_real:
        kept_real_part()
    elif not args.skip_real:
        real_part(args, rng)
    if args.keep_generated:
        kept_generated_part()
    else:
        generated_part(args, rng)
    print(f"\n({time.perf_counter() - t0:.0f} s)")
    return 0
