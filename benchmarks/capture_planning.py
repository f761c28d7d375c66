"""Capture planning: measurements needed to pin down roughness, D-optimal vs random vs uniform.

    python benchmarks/capture_planning.py [--materials 4] [--candidates 400] [--target 0.05]
    python benchmarks/capture_planning.py --flash ...   (a flash capture: _flash_planning.py)

Synthetic materials (diffuse + GGX lobe with Schlick Fresnel, RGB albedo, grey F0, alpha in
0.05 ... 0.4), a fixed candidate set of light/view pairs within 75 degrees of the normal, a
noise std of 1% of the material's mean f_r, three random pairs measured to start. A
strategy picks the next pair among the candidates not yet measured:

* ``d-optimal``: refit the material to what was measured so far (``fit_pixels``; the
  unmeasured slots have weight 0, so one compiled fit serves every step) and take the
  candidate with the largest expected information gain at that estimate
  (:func:`jaxrefl.measured.rank_candidates`);
* ``d-optimal (truth)``: the same at the true parameters (the locally optimal design,
  no refit; a bound for the sequential one);
* ``random``: a random order (mean over 10 orders);
* ``uniform``: farthest-point order over the candidates in (wi, wo) space, i.e. coverage as
  even as the candidate set allows.

Score: measurements (start included) until the Laplace std of ln alpha, from the Fisher
information at the truth, is at most ``--target``; the ratios random / d-optimal and
uniform / d-optimal are the savings of planning.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, run_and_record, table  # noqa: E402

from jaxrefl.fit import fit_pixels, pixel_data  # noqa: E402
from jaxrefl.measured import Components, information, rank_candidates  # noqa: E402
from jaxrefl.measured._components import param_space  # noqa: E402
from jaxrefl.measured._plan import PRIOR_WIDTH, posterior_std  # noqa: E402

START = 3


def _hemi(rng, n, theta_max_deg=75.0):
    u = rng.uniform(np.cos(np.radians(theta_max_deg)), 1.0, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    s = np.sqrt(1 - u * u)
    return np.stack([s * np.cos(phi), s * np.sin(phi), u], -1)


def farthest_point_order(x: np.ndarray, first: int = 0) -> np.ndarray:
    """Indices of ``x`` (M, D), each the farthest from all chosen before."""
    order = [first]
    d = np.linalg.norm(x - x[first], axis=-1)
    for _ in range(len(x) - 1):
        k = int(np.argmax(d))
        order.append(k)
        d = np.minimum(d, np.linalg.norm(x - x[k], axis=-1))
    return np.asarray(order)


def needed(info: np.ndarray, order, ia: int, target: float) -> int:
    a = np.eye(info.shape[-1]) / PRIOR_WIDTH**2
    for n, k in enumerate(order, start=1):
        a = a + info[k]
        if posterior_std(a)[ia] <= target:
            return n
    return len(order) + 1  # never reached within the candidate set


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--materials", type=int, default=4)
    ap.add_argument("--candidates", type=int, default=400)
    ap.add_argument("--target", type=float, default=0.05, help="std of ln alpha")
    ap.add_argument("--max", type=int, default=80, help="measurement budget per strategy")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    m = args.candidates
    cwi, cwo = _hemi(rng, m), _hemi(rng, m)
    model = Components().build()
    space = param_space(model, 3, grey=("specular",))
    ia = space.labels.index("alpha")
    uniform = farthest_point_order(np.concatenate([cwi, cwo], axis=1))
    alphas = np.geomspace(0.05, 0.4, args.materials)
    rows, ratios_r, ratios_u = [], [], []
    for j, alpha in enumerate(alphas):
        truth = {
            "albedo": rng.uniform(0.1, 0.6, 3),
            "specular": np.full(3, rng.uniform(0.04, 0.1)),
            "alpha": np.asarray(alpha),
        }
        theta_true = space.from_natural(truth)
        f = np.asarray(model.eval({k: jnp.asarray(v) for k, v in truth.items()}, cwi, cwo))
        sigma = 0.01 * float(np.mean(f))
        obs = f + sigma * rng.standard_normal(f.shape)
        info = information(model, space, theta_true, cwi, cwo, sigma=sigma)
        start = list(rng.choice(m, START, replace=False))

        # Sequential D-optimal with a refit after every measurement.
        measured = list(start)
        n_seq = args.max + 1
        for step in range(args.max - START + 1):
            if needed(info, measured, ia, args.target) <= len(measured):
                n_seq = len(measured)
                break
            w = np.zeros((m, 3))
            w[measured] = 1.0
            data = pixel_data(obs[None], cwi[None], cwo[None], weight=w[None])
            fit = fit_pixels(model, data, space=space)
            theta = np.asarray(fit.theta[0])
            if not np.all(np.isfinite(theta)):
                theta = np.asarray(space.default_theta(jnp.float64))
            r = rank_candidates(
                model,
                space,
                jnp.asarray(theta),
                cwi,
                cwo,
                measured_wi=cwi[measured],
                measured_wo=cwo[measured],
                sigma=sigma,
            )
            nxt = next(int(k) for k in r.order if int(k) not in measured)
            measured.append(nxt)
            del step
        # D-optimal at the truth (greedy, without repeats).
        a = np.eye(space.size) / PRIOR_WIDTH**2 + info[start].sum(axis=0)
        oracle = list(start)
        for _ in range(args.max - START):
            gain = np.linalg.slogdet(a[None] + info)[1]
            gain[oracle] = -np.inf
            k = int(np.argmax(gain))
            oracle.append(k)
            a = a + info[k]
        n_oracle = needed(info, oracle, ia, args.target)
        n_rand = float(
            np.mean(
                [
                    needed(
                        info,
                        start
                        + [
                            int(k)
                            for k in np.random.default_rng(s).permutation(m)
                            if k not in start
                        ],
                        ia,
                        args.target,
                    )
                    for s in range(10)
                ]
            )
        )
        n_uni = needed(info, start + [int(k) for k in uniform if k not in start], ia, args.target)
        ratios_r.append(n_rand / n_seq)
        ratios_u.append(n_uni / n_seq)
        rows.append(
            [
                j,
                f"{alpha:.3f}",
                n_seq,
                n_oracle,
                f"{n_rand:.1f}",
                n_uni,
                f"{n_rand / n_seq:.2f}",
                f"{n_uni / n_seq:.2f}",
            ]
        )
    print(f"# Measurements until std(ln alpha) <= {args.target} ({m} candidates, start {START})")
    print(f"machine: {machine()}\n")
    print(
        table(
            [
                "material",
                "alpha",
                "d-optimal",
                "d-optimal (truth)",
                "random (mean of 10)",
                "uniform",
                "random / d-opt",
                "uniform / d-opt",
            ],
            rows,
        )
    )
    print(
        f"\nmean ratio random / d-optimal {np.mean(ratios_r):.2f}, "
        f"uniform / d-optimal {np.mean(ratios_u):.2f}  ({time.perf_counter() - t0:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    if "--flash" in sys.argv:  # the flash-capture part (benchmarks/_flash_planning.py)
        from _flash_planning import main as flash_main

        sys.exit(
            run_and_record(
                "capture_planning_flash",
                "Capture planning for a flash capture",
                lambda: flash_main(sys.argv[1:]),
                script="capture_planning.py --flash",
            )
        )
    sys.exit(run_and_record("capture_planning", "Capture planning", main))
