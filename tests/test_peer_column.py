"""The peer column of ``benchmarks/real_captures.py``: held-out errors scored raw and clamped
to [0, 1] (what a renderer displays, the Adam peer's own output), over each held-out photo's
uncensored observations."""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.fixture
def real_captures(monkeypatch):
    """The script's module; the XLA flags its import sets are put back afterwards."""
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    return importlib.import_module("real_captures")


def test_scores_clamp_what_a_renderer_clamps_and_skip_censored(real_captures):
    """Photo 0 predicted at 2 where it is 1 (past white), photo 1 at -0.5 where it is 0 but
    for one censored pixel predicted 0.5: raw errors 1 and 0.5, clamped 0 and 0."""
    k, h, w, c = 2, 2, 2, 1
    images = np.zeros((k, h, w, c))
    images[0] = 1.0
    status = np.zeros((k, h, w, c), int)
    status[1, 0, 0, 0] = 1  # censored: not scored
    preds = {0: np.full((h, w, c), 2.0), 1: np.full((h, w, c), -0.5)}
    preds[1][0, 0, 0] = 0.5
    cap = SimpleNamespace(shape=(k, h, w, c), images=images, status=status)
    s = real_captures._scores(cap, preds)
    np.testing.assert_allclose(s["raw"]["per_photo"], [1.0, 0.5])
    np.testing.assert_allclose(s["clamped"]["per_photo"], [0.0, 0.0])
    assert s["clamped"]["p99"] == 0.0 and s["raw"]["p99"] > 0.5
