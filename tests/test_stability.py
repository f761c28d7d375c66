"""The stability sweep (see ``benchmarks/_stability_sweep.py``): zero non-finite values or
gradients over every model, every edge case, float32 and float64."""

from __future__ import annotations

import sys
from pathlib import Path

import jax.numpy as jnp
import pytest

from jaxrefl.brdf import model_zoo

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _stability_sweep import edge_directions, parameter_sets, run_stability

ZOO = model_zoo()


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
def test_stability_sweep_all_finite(dtype):
    rows = run_stability(ZOO, dtypes=(dtype,))
    assert len(rows) == len(ZOO) + 3
    bad = [r for r in rows if r.nonfinite_values or r.nonfinite_grads]
    assert not bad, "\n".join(str(r) for r in bad)
    assert sum(r.cases for r in rows) > 1000


def test_sweep_covers_the_issue_edges():
    _, _, labels = edge_directions()
    assert any("cos = 0" in s for s in labels) and any("grazing" in s for s in labels)
    m = ZOO[[e.label for e in ZOO].index("ct_ggx_smith_height_correlated_schlick")].build()
    names = [n for n, _ in parameter_sets(m)]
    assert "alpha=0.0001" in names and "alpha=1" in names
