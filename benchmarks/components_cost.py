"""What a component costs: a diffuse-only scene against one with a specular lobe.

    python benchmarks/components_cost.py [--pixels 20000] [--lights 16]

Three models of :class:`jaxrefl.measured.Components`, on N pixels x K lights x 3 channels:

* ``diffuse``: the assembly with only the diffuse base (compiles to albedo / pi);
* ``diffuse, lobe off``: diffuse + GGX lobe with the lobe's strength fixed at 0 and its
  width fixed (what a model with a flag instead of components pays: the same fit, the
  lobe still computed);
* ``diffuse + lobe``: diffuse + GGX lobe, all parameters free.

Per model: compile time (first call minus a warm one), warm time of a jitted forward
evaluation (median of 5) and of a batched fit (``jaxrefl.fit.fit_pixels``, lean LM, float32),
and both as ratios to the diffuse-only model measured in the same run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, run_and_record, table

from jaxrefl.fit import FitConfig, LMOptions, fit_pixels, pixel_data
from jaxrefl.measured import Components
from jaxrefl.measured._components import param_space

CONFIG = FitConfig(solver=LMOptions(max_iters=20))


def _timed(fn, repeats: int = 5) -> tuple[float, float]:
    """(compile s, warm s): first call minus the median of ``repeats`` warm calls."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    warm = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        warm.append(time.perf_counter() - t0)
    w = float(np.median(warm))
    return max(first - w, 0.0), w


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--pixels", type=int, default=20_000)
    ap.add_argument("--lights", type=int, default=16)
    args = ap.parse_args()
    n, k = args.pixels, args.lights
    rng = np.random.default_rng(0)
    wi = rng.normal(size=(n, k, 3))
    wi[..., 2] = np.abs(wi[..., 2]) + 0.1
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wi = jnp.asarray(wi, jnp.float32)
    wo = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], jnp.float32), wi.shape)
    albedo = jnp.asarray(rng.uniform(0.2, 0.8, (n, 1, 3)), jnp.float32)
    obs = albedo / jnp.pi * jnp.ones((1, k, 1), jnp.float32)
    data = pixel_data(obs, wi, wo)

    alpha = jnp.full((n, 1), 0.2, jnp.float32)
    diffuse = Components(lobe=None, fresnel=False).build()
    lobe = Components(fresnel=False).build()
    cases = [
        ("diffuse", diffuse, {"albedo": albedo}, {}),
        (
            "diffuse, lobe off",
            lobe,
            {"albedo": albedo, "specular": jnp.zeros((n, 1, 3)), "alpha": alpha},
            {"specular": 0.0, "alpha": 0.2},
        ),
        (
            "diffuse + lobe",
            lobe,
            {
                "albedo": albedo,
                "specular": jnp.full((n, 1, 3), 0.05),
                "alpha": jnp.full((n, 1), 0.2),
            },
            {},
        ),
    ]
    rows, base = [], None
    for label, model, params, fixed in cases:
        ev = jax.jit(model.eval)
        c_eval, t_eval = _timed(lambda m=ev, p=params: m(p, wi, wo))
        space = param_space(model, 3, fixed=fixed or None)
        c_fit, t_fit = _timed(
            lambda m=model, s=space: fit_pixels(m, data, config=CONFIG, space=s).theta, repeats=3
        )
        if base is None:
            base = (t_eval, t_fit)
        rows.append(
            [
                label,
                space.size,
                f"{c_eval:.2f}",
                f"{1e3 * t_eval:.1f}",
                f"{t_eval / base[0]:.2f}",
                f"{c_fit:.1f}",
                f"{1e3 * t_fit:.0f}",
                f"{t_fit / base[1]:.2f}",
            ]
        )
    print(f"# Cost of a specular lobe ({n} pixels x {k} lights x 3 channels, float32)")
    print(f"machine: {machine()}\n")
    print(
        table(
            [
                "model",
                "free P",
                "eval compile s",
                "eval ms",
                "eval / diffuse",
                "fit compile s",
                "fit ms",
                "fit / diffuse",
            ],
            rows,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(run_and_record("components_cost", "What each model component costs", main))
