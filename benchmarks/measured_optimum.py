"""Measured-BRDF fits: does the default fit reach the optimum that many random starts find?

For every file in ``../shared/data/brdf`` (the two Cornell files, converted to linear sRGB
under D65, and every CURET sample of ``abrdf.dat``) and every model of the default set
(:data:`jaxrefl.measured.DEFAULT_MODELS`; on the Cornell files also the Cook-Torrance
models with the exact dielectric Fresnel term and a fitted eta), samples within 80 degrees:

* ``default``: :func:`jaxrefl.measured.fit_model` as ``jaxrefl fit-brdf`` runs it (the
  data-driven and 24 quasi-random starts solved together, for Lafortune with L lobes also
  the nested starts from the (L-1)-lobe fit; starts stopped at the iteration budget
  continued, and perturbed generations of the best while the starts disagree; float64
  retry), its certificate;
* ``best of 64``: 64 independent uniform starts in the same box of the unconstrained space
  (another seed, :func:`jaxrefl.measured.random_thetas` with ``sobol=False``), solved
  together with a 200-iteration budget (continued, as every multi-start fit is, while its
  best starts stop at the budget; no perturbed generations), the best kept.

Both costs are 1/2 sum ((f_hat - f) cos theta_i)^2 over samples and channels, evaluated in
float64 at each fit's parameters; ``gap`` = (default - best of 64) / best of 64 (negative:
the default found the lower cost). Times: wall seconds of the default fit without the
compilation of the model's first fit (printed apart) and, for a nested model, without the
fit of the smaller model it starts from (a row of its own).

    python benchmarks/measured_optimum.py [--curet all|N,M,...] [--rows FILE] [--no-write]

It prints the tables and writes them, dated and with the machine, to the section
``measured_optimum`` of ``docs/benchmarks.md``, after every material (a long run leaves
what it has measured). ``--rows FILE`` keeps every measured row in a JSON-lines file and
skips the (file, model) pairs already there, so that an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _common import machine, table, write_section  # noqa: E402

from jaxrefl import fit  # noqa: E402
from jaxrefl import measured as jm  # noqa: E402
from jaxrefl.measured._nested import nested_model  # noqa: E402
from jaxrefl.measured._seeds import random_thetas  # noqa: E402

DATA = Path(os.environ.get("JAXREFL_SHARED_DATA", HERE.parent.parent / "shared" / "data"))
N_REF = 64
REF_SEED = 1
REF_ITERS = 200
TOL = 0.01
EXTRA_CORNELL = ("beckmann_dielectric", "ggx_dielectric")
# The materials are restricted to 80 degrees as they are read (_materials): every sample of
# them is fitted.
ALL_SAMPLES = jm.MeasuredOptions(max_theta_deg=None)


def _cost(result: fit.FitResult, m) -> float:
    f_hat = jm.predict(result, m.wi, m.wo)
    d = (f_hat - np.asarray(m.values)) * m.wi[:, 2:3]
    return float(0.5 * np.sum(d * d))


def _reference(model, m) -> float:
    space = fit.ParamSpace(model, channels=len(m.channels))
    thetas = random_thetas(space, N_REF, REF_SEED, sobol=False)
    cfg = fit.FitConfig(solver=fit.LMOptions(max_iters=REF_ITERS), dtype=np.float32)
    r, _, _ = jm.fit_multistart(model, m, options=ALL_SAMPLES, config=cfg, thetas=thetas)
    return _cost(r, m)


def _materials(curet: str):
    for name in ("acryl_blue", "krylon_blue"):
        m = jm.load_measured(DATA / "brdf" / "cornell" / f"{name}.astm")
        yield f"cornell/{name}", jm.restrict(jm.to_rgb(m), 80.0), True
    ids = range(1, 62) if curet == "all" else [int(s) for s in curet.split(",") if s]
    for i in ids:
        m = jm.load_measured(DATA / "brdf" / "curet" / "abrdf.dat", curet_sample=i)
        yield f"curet/{i}", jm.restrict(m, 80.0), False


def _body(rows, curet_rows, compile_s, n_curet: int) -> str:
    def fmt(r):
        gap = f"{100 * r[4]:+.2f}%"
        return [r[0], r[1], f"{r[2]:.5g}", f"{r[3]:.5g}", gap, r[5], f"{r[6]:.2f}"]

    head = ["file", "model", "default cost", f"best of {N_REF}", "gap", "starts agree", "fit s"]
    parts = [
        f"### Measured fits against the best of {N_REF} random starts "
        f"({datetime.date.today().isoformat()})",
        "",
        f"machine: {machine()}",
        "",
        "Cost 1/2 sum ((f_hat - f) cos theta_i)^2 (float64, samples within 80 degrees); gap = "
        f"(default - best of {N_REF}) / best of {N_REF}; starts agree: starts within 1% of "
        "the default fit's best (doubtful: below the stated share, 20%).",
        "",
        "Cornell files (linear sRGB under D65), every default model and the dielectric "
        "Cook-Torrance variants:",
        "",
        table(head, [fmt(r) for r in rows]),
    ]
    if curet_rows:
        summary = []
        for name in jm.DEFAULT_MODELS:
            rs = [r for r in curet_rows if r[1] == name]
            if not rs:
                continue
            gaps = np.array([r[4] for r in rs])
            worst = rs[int(np.argmax(gaps))]
            doubt = sum("doubtful" in r[5] for r in rs)
            summary.append(
                [
                    name,
                    len(rs),
                    int(np.sum(gaps <= TOL)),
                    f"{100 * np.max(gaps):+.2f}% ({worst[0]})",
                    f"{100 * np.median(gaps):+.3f}%",
                    doubt,
                    f"{np.median([r[6] for r in rs]):.2f}",
                ]
            )
        done = len({r[0] for r in curet_rows})
        parts += [
            "",
            f"CURET samples ({done} of {n_curet}), per model:",
            "",
            table(
                ["model", "samples", "within 1%", "worst gap", "median gap", "doubtful",
                 "median fit s"],
                summary,
            ),
        ]  # fmt: skip
        beyond = [fmt(r) for r in curet_rows if r[4] > TOL]
        if beyond:
            parts += ["", "CURET fits more than 1% above the best of 64:", "", table(head, beyond)]
    all_rows = rows + curet_rows
    n_bad = sum(r[4] > TOL for r in all_rows)
    parts += [
        "",
        f"{len(all_rows) - n_bad} of {len(all_rows)} fits within 1% of the best of {N_REF}.",
    ]
    if compile_s:
        parts += [
            "",
            "Compile time of each model's first default fit (s; Cornell, then CURET shapes): "
            + ", ".join(f"{k[0]} {v:.1f} ({k[1]})" for k, v in compile_s.items()),
        ]
    return "\n".join(parts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--curet", default="all", help="CURET samples: all, or e.g. 1,5,12")
    ap.add_argument("--rows", type=Path, default=None, help="JSON-lines file of measured rows")
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)
    print(f"machine: {machine()}\n")
    n_curet = 61 if args.curet == "all" else len(args.curet.split(","))
    kept: dict[tuple[str, str], list] = {}
    if args.rows is not None and args.rows.exists():
        for line in args.rows.read_text().splitlines():
            r = json.loads(line)
            kept[(r[0], r[1])] = r
    compile_s: dict[tuple[str, str], float] = {}
    rows, curet_rows = [], []
    for label, m, cornell in _materials(args.curet):
        names = jm.DEFAULT_MODELS + (EXTRA_CORNELL if cornell else ())
        done: dict[str, jm.ModelFit] = {}
        for name in names:
            if (label, name) in kept:
                (rows if cornell else curet_rows).append(kept[(label, name)])
                continue
            model = jm.build_model(name)
            inner = nested_model(model)
            # As fit-brdf: a nested model starts from the fit of the smaller one (when that
            # row was resumed from --rows, fit_model fits the smaller one itself).
            seed = next((v for v in done.values() if v.model == inner), None)
            t0 = time.perf_counter()
            mf = jm.fit_model(model, m, name=name, options=ALL_SAMPLES, timing=False, nested=seed)
            dt = time.perf_counter() - t0
            key = (name, label.split("/")[0])
            if key not in compile_s:
                # The first fit of a model on a file's shapes compiles it: time it again,
                # warm, to split the two.
                t1 = time.perf_counter()
                jm.fit_model(model, m, name=name, options=ALL_SAMPLES, timing=False, nested=seed)
                warm = time.perf_counter() - t1
                compile_s[key] = max(dt - warm, 0.0)
                dt = warm
            done[name] = mf
            ref = _reference(model, m)
            gap = (mf.cost - ref) / ref if ref > 0 else 0.0
            cert = mf.certificate
            row = [label, name, mf.cost, ref, gap, cert.short() if cert else "-", dt]
            (rows if cornell else curet_rows).append(row)
            if args.rows is not None:
                with args.rows.open("a") as fh:
                    fh.write(json.dumps(row) + "\n")
            print(
                f"{label:22s} {name:34s} {mf.cost:10.4g} {ref:10.4g} {100 * gap:+7.2f}% "
                f"{row[5]:>14s} {dt:6.2f} s",
                flush=True,
            )
        if not args.no_write:
            write_section("measured_optimum", _body(rows, curet_rows, compile_s, n_curet))
    body = _body(rows, curet_rows, compile_s, n_curet)
    print("\n" + body)
    if not args.no_write:
        print(f"wrote {write_section('measured_optimum', body)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
