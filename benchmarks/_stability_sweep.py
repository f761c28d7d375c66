"""Stability sweep: values and gradients at the edges of every model's domain.

For each model in the zoo and each dtype (float32, float64) the sweep evaluates f_r and
``jax.grad`` of f_r with respect to every parameter on a grid of *cases*:

* parameter sets: the defaults, then one parameter at a time at each of its edge values
  (roughness 1e-4 .. 1, exponents 0 .. 1e5, eta 1.0001 .. 4, k 0 .. 10, sigma 0 .. 1.5,
  colours 0 and 1) plus one set with every parameter at its hardest edge at once;
* direction pairs: normal incidence (wi = wo = n, so wh ∥ n), wi = wo at 45°, a mirror pair
  (wh ∥ n), grazing cos θ = 1e-6 for one or both directions (including the grazing mirror
  pair and wi = wo grazing), cos θ = 0 exactly, below the horizon, and random pairs.

It also sweeps the Fresnel functions on their own: dielectric with eta 1.0001 .. 4 and its
inverse (total internal reflection from inside), conductor with k up to 10, and Schlick.

A case is *finite* when every value and every gradient component is finite. The sweep is
used by ``benchmarks/stability.py`` (the printed table), ``paper_figures/`` (the CSV) and
``tests/test_stability.py`` (which requires zero non-finite cases); it is a harness, not part
of the library, so it lives here and uses only the public API of ``jaxrefl.brdf``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl.brdf import (
    BRDF,
    ZooEntry,
    fresnel_conductor,
    fresnel_dielectric,
    fresnel_schlick,
    model_zoo,
)

__all__ = ["EDGE_VALUES", "StabilityRow", "edge_directions", "run_stability"]

# Edge values for each parameter of the shared vocabulary.
EDGE_VALUES: dict[str, tuple[float, ...]] = {
    "alpha": (1e-4, 1e-3, 1e-2, 0.1, 0.5, 1.0),
    "alpha_u": (1e-4, 1e-2, 1.0),
    "alpha_v": (1e-4, 1e-2, 1.0),
    "exponent": (0.0, 1.0, 100.0, 1e4, 1e5),
    "eta": (1.0001, 1.01, 1.5, 2.5, 4.0),
    "k": (0.0, 0.5, 3.0, 10.0),
    "sigma": (0.0, 0.1, 0.5, 1.5),
    "albedo": (0.0, 1.0),
    "specular": (0.0, 0.04, 1.0),
}
# The hardest value of each parameter, used all at once in one extra set.
HARDEST: dict[str, float] = {
    "alpha": 1e-4,
    "alpha_u": 1e-4,
    "alpha_v": 1.0,
    "exponent": 1e5,
    "eta": 1.0001,
    "k": 10.0,
    "sigma": 1.5,
    "albedo": 1.0,
    "specular": 1.0,
}
LOBE_EXPONENTS = (0.0, 1.0, 100.0, 1e4, 1e5)


def edge_directions() -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Direction pairs (wi, wo), shape (D, 3) each, float64, with labels."""
    g = 1e-6  # grazing cosine
    s = np.sqrt(1.0 - g * g)
    c45 = np.sqrt(0.5)
    pairs = [
        ("normal, wi = wo", (0, 0, 1), (0, 0, 1)),
        ("wi = wo at 45 deg", (c45, 0, c45), (c45, 0, c45)),
        ("mirror pair 60 deg (wh = n)", (0.866025403784, 0, 0.5), (-0.866025403784, 0, 0.5)),
        ("grazing wi, normal wo", (s, 0, g), (0, 0, 1)),
        ("normal wi, grazing wo", (0, 0, 1), (0, s, g)),
        ("grazing mirror pair (wh = n)", (s, 0, g), (-s, 0, g)),
        ("wi = wo grazing", (s, 0, g), (s, 0, g)),
        ("grazing, 90 deg apart", (s, 0, g), (0, s, g)),
        ("wi on the horizon (cos = 0)", (1, 0, 0), (0, 0, 1)),
        ("both on the horizon", (1, 0, 0), (-1, 0, 0)),
        ("wi below the horizon", (0.6, 0, -0.8), (0, 0, 1)),
    ]
    rng = np.random.default_rng(7)
    for j in range(5):
        a = rng.normal(size=(2, 3))
        a[:, 2] = np.abs(a[:, 2])
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        pairs.append((f"random pair {j}", tuple(a[0]), tuple(a[1])))
    labels = [p[0] for p in pairs]
    wi = np.array([p[1] for p in pairs], dtype=np.float64)
    wo = np.array([p[2] for p in pairs], dtype=np.float64)
    return wi, wo, labels


def _lobe_sets(default: np.ndarray) -> list[np.ndarray]:
    n_lobes = default.shape[-2]
    shapes = [(-1.0, -1.0, 1.0), (1.0, 1.0, 1.0), (-1.0, -0.2, 0.8), (-1.1, -1.1, 0.0)]
    sets = []
    for c, n in itertools.product(shapes, LOBE_EXPONENTS):
        sets.append(np.tile(np.array([*c, n]), (n_lobes, 1)))
    return sets


def parameter_sets(model: BRDF) -> list[tuple[str, dict[str, np.ndarray]]]:
    """Defaults, one-at-a-time edge values, and all-hardest-at-once."""
    base = {
        k: np.asarray(v, dtype=np.float64) for k, v in model.default_params(jnp.float64).items()
    }
    sets: list[tuple[str, dict[str, np.ndarray]]] = [("defaults", base)]
    hardest = dict(base)
    for q in model.params:
        if q.kind == "lobes":
            for j, lobes in enumerate(_lobe_sets(base[q.name])):
                sets.append((f"{q.name}#{j}", {**base, q.name: lobes}))
            hardest[q.name] = _lobe_sets(base[q.name])[4]  # mirror lobe with n = 1e5
            continue
        for v in EDGE_VALUES.get(q.name, (q.lower, q.upper)):
            if not (q.lower <= v <= q.upper):
                continue  # an edge value outside this model's stated range is not a case
            sets.append((f"{q.name}={v:g}", {**base, q.name: np.full_like(base[q.name], v)}))
        if q.name in HARDEST and q.lower <= HARDEST[q.name] <= q.upper:
            hardest[q.name] = np.full_like(base[q.name], HARDEST[q.name])
    sets.append(("all hardest", hardest))
    return sets


@dataclass
class StabilityRow:
    label: str
    dtype: str
    cases: int
    nonfinite_values: int
    nonfinite_grads: int
    max_abs_value: float
    max_abs_grad: float


def _stack_sets(sets: list[dict[str, np.ndarray]], dtype) -> dict[str, jax.Array]:
    return {k: jnp.asarray(np.stack([s[k] for s in sets]), dtype=dtype) for k in sets[0]}


def _check_model(model: BRDF, dtype) -> tuple[int, int, int, float, float]:
    wi_np, wo_np, _ = edge_directions()
    sets = [s for _, s in parameter_sets(model)]
    P, D = len(sets), wi_np.shape[0]
    params = _stack_sets(sets, dtype)
    wi = jnp.asarray(wi_np, dtype=dtype)
    wo = jnp.asarray(wo_np, dtype=dtype)

    def value_and_grads(p, a, b):
        # One trace and one compilation give f and the gradient of sum(f) (via the VJP).
        f, vjp = jax.vjp(lambda q: model.eval(q, a, b), p)
        return f, vjp(jnp.ones_like(f))[0]

    over_dirs = jax.vmap(value_and_grads, in_axes=(None, 0, 0))
    f, g = jax.jit(jax.vmap(over_dirs, in_axes=(0, None, None)))(params, wi, wo)  # (P, D, C)
    f = np.asarray(f).reshape(P, D, -1)
    bad_v = ~np.all(np.isfinite(f), axis=-1)
    bad_g = np.zeros((P, D), dtype=bool)
    gmax = 0.0
    for leaf in jax.tree_util.tree_leaves(g):
        arr = np.asarray(leaf).reshape(P, D, -1)
        bad_g |= ~np.all(np.isfinite(arr), axis=-1)
        fin = arr[np.isfinite(arr)]
        if fin.size:
            gmax = max(gmax, float(np.max(np.abs(fin))))
    fin_f = f[np.isfinite(f)]
    return P * D, int(bad_v.sum()), int(bad_g.sum()), float(np.max(np.abs(fin_f))), gmax


def _check_fresnel(dtype) -> list[StabilityRow]:
    cos = np.array([1.0, 0.5, 1e-3, 1e-6, 0.0, -1e-6, -0.5, -1.0])
    etas = np.array([1.0001, 1.01, 1.5, 2.5, 4.0, 1 / 1.5, 1 / 4.0])
    ks = np.array([0.0, 0.5, 3.0, 10.0])
    rows = []

    def run(label, fn, args):
        grid = np.meshgrid(*args, indexing="ij")
        flat = [jnp.asarray(a.reshape(-1), dtype=dtype) for a in grid]
        v = jax.jit(fn)(*flat)
        gs = jax.jit(jax.vmap(jax.grad(fn, argnums=tuple(range(len(flat))))))(*flat)
        v = np.asarray(v)
        bad_v = ~np.isfinite(v)
        bad_g = np.zeros_like(bad_v)
        gmax = 0.0
        for gg in gs:
            gg = np.asarray(gg)
            bad_g |= ~np.isfinite(gg)
            if np.isfinite(gg).any():
                gmax = max(gmax, float(np.max(np.abs(gg[np.isfinite(gg)]))))
        rows.append(
            StabilityRow(
                label,
                jnp.dtype(dtype).name,
                v.size,
                int(bad_v.sum()),
                int(bad_g.sum()),
                float(np.max(np.abs(v[np.isfinite(v)]))),
                gmax,
            )
        )

    run("fresnel_dielectric (incl. TIR)", fresnel_dielectric, (cos, etas))
    run("fresnel_conductor", lambda c, e, k: fresnel_conductor(jnp.abs(c), e, k), (cos, etas, ks))
    run(
        "fresnel_schlick",
        lambda c, f0: fresnel_schlick(jnp.abs(c), f0),
        (cos, np.array([0.0, 0.04, 1.0])),
    )
    return rows


def run_stability(
    zoo: list[ZooEntry] | None = None, dtypes=(jnp.float32, jnp.float64)
) -> list[StabilityRow]:
    """Run the sweep; float64 rows need ``jax_enable_x64``."""
    rows = []
    zoo = model_zoo() if zoo is None else zoo
    for dtype in dtypes:
        for entry in zoo:
            n, bv, bg, fmax, gmax = _check_model(entry.build(), dtype)
            rows.append(StabilityRow(entry.label, jnp.dtype(dtype).name, n, bv, bg, fmax, gmax))
        rows.extend(_check_fresnel(dtype))
    return rows
