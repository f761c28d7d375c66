"""Single-material posteriors with default settings: do they converge, and how long do they take?

For each Cornell file in ``../shared/data/brdf/cornell`` (converted to linear sRGB) and each
model given, :func:`jaxrefl.measured.sample_posterior` with its defaults, as
``jaxrefl sample FILE`` runs it: the multi-start least-squares fit, then emcee until the
chain is at least 50 integrated autocorrelation times long with rank-normalised split R-hat
<= 1.01 and bulk ESS >= 400 for every parameter, or its cap on steps. Printed per file:
the chain's length in steps and in units of the largest tau, the worst R-hat and bulk ESS
over the parameters (ArviZ's estimators, walkers as chains), whether it converged, and
wall seconds of the fit and of sampling (the log density's compilation printed apart).
Then PSIS-LOO of the models on each file from the ``posterior.nc`` the command writes
(``az.compare``: elpd_loo, its difference to the best and that difference's standard
error, the largest Pareto k and how many observations have k > 0.7, where PSIS-LOO is
unreliable for that observation).

    python benchmarks/measured_posterior.py [--models ggx,lambert] [--no-write]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from _common import run_and_record, table  # noqa: E402

from jaxrefl import measured as jm  # noqa: E402

DATA = Path(os.environ.get("JAXREFL_SHARED_DATA", HERE.parent.parent / "shared" / "data"))
FILES = ("acryl_blue", "krylon_blue")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="ggx,lambert", help="comma-separated model names")
    args = ap.parse_args()
    models = args.models.split(",")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az

    rows, loo_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name in FILES:
            path = DATA / "brdf" / "cornell" / f"{name}.astm"
            written = {}
            for model in models:
                t0 = time.perf_counter()
                res = jm.sample_posterior(path, model)
                wall = time.perf_counter() - t0
                c = res.convergence
                tau = max(c.tau)
                rows.append(
                    [
                        name,
                        model,
                        c.n_steps,
                        f"{tau:.0f}",
                        f"{c.n_steps / tau:.0f}",
                        f"{c.max_rhat:.4f}",
                        f"{c.min_ess_bulk:.0f}",
                        "yes" if c.converged else "NO: " + "; ".join(c.reasons),
                        f"{res.timings['fit_s']:.0f}",
                        f"{res.samples.run_s:.0f}",
                        f"{res.samples.compile_s:.1f}",
                        f"{wall:.0f}",
                    ]
                )
                out = Path(tmp) / f"{name}_{model}"
                jm.write_posterior(res, out)
                written[model] = az.from_netcdf(str(out / "posterior.nc"))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # Pareto k > 0.7: in the table
                cmp = az.compare(written)
                ks = {m: az.loo(written[m], pointwise=True).pareto_k for m in written}
            for model, r in cmp.iterrows():
                k = ks[str(model)]
                loo_rows.append(
                    [
                        name,
                        model,
                        int(r["rank"]),
                        f"{r['elpd_loo']:.1f}",
                        f"{r['elpd_diff']:.1f}",
                        f"{r['dse']:.1f}",
                        f"{float(k.max()):.2f}",
                        int((k > 0.7).sum()),
                    ]
                )
    print("### Convergence with default settings\n")
    heads = ["file", "model", "steps", "max tau", "steps / tau", "max R-hat", "min bulk ESS"]
    heads += ["converged", "fit s", "sampling s", "compile s", "total s"]
    print(table(heads, rows))
    print("\n### PSIS-LOO from posterior.nc (az.compare)\n")
    heads = ["file", "model", "rank", "elpd_loo", "elpd_diff", "dse", "max Pareto k", "k > 0.7"]
    print(table(heads, loo_rows))
    return 0


if __name__ == "__main__":
    sys.exit(run_and_record("measured_posterior", "Single-material posteriors", main))
