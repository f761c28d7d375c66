"""``Samples`` carries its run facts as typed fields: ``no_estimate`` follows the pixels
through ``take``, ``concat`` and a chunk file; the settings that ran (``reparam``,
``options``, ``gibbs``, ``sweeps``) are the first part's; a chunk file keeps
``no_estimate`` and ``reparam``, and nothing else of them."""

from __future__ import annotations

import numpy as np

import jaxrefl.posterior as jp
from jaxrefl.posterior._chunk_files import fingerprint, load_chunk, open_pass, save_chunk

LABELS = ("a", "b")


def _samples(n: int, offset: float, no_estimate=None, **kw) -> jp.Samples:
    c, m, d = 2, 3, len(LABELS)
    x = offset + np.arange(n * c * m * d, dtype=np.float64).reshape(n, c, m, d)
    st = {"acceptance_rate": np.ones((n, c, m)), "diverging": np.zeros((n, c, m), bool)}
    if no_estimate is not None:
        kw["no_estimate"] = np.asarray(no_estimate, bool)
    return jp.Samples(
        x, x, LABELS, st, "hmc", {"step_size": np.full((n, c), offset)}, run_s=1.0, **kw
    )


def test_no_estimate_left_out_means_every_pixel_has_one():
    s = _samples(3, 0.0)
    assert s.no_estimate.dtype == bool and s.no_estimate.shape == (3,)
    assert not s.no_estimate.any()
    assert s.reparam == "none" and s.options is s.gibbs is s.sweeps is s.emcee is None


def test_take_and_concat_slice_no_estimate_per_pixel():
    opts, gibbs = jp.HMCOptions(num_chains=2), jp.GibbsOptions()
    a = _samples(
        3, 0.0, [False, True, False], reparam="albedo", options=opts, gibbs=gibbs, sweeps=4
    )
    b = _samples(2, 100.0, [True, False])
    head = a.take(2)
    np.testing.assert_array_equal(head.no_estimate, [False, True])
    np.testing.assert_array_equal(head.theta, a.theta[:2])
    picked = a.take(np.array([2, 1]))
    np.testing.assert_array_equal(picked.no_estimate, [False, True])
    np.testing.assert_array_equal(picked.tuning["step_size"], a.tuning["step_size"][[2, 1]])
    assert (picked.reparam, picked.options, picked.gibbs, picked.sweeps) == (
        "albedo",
        opts,
        gibbs,
        4,
    )
    joined = jp.Samples.concat([a, b])
    np.testing.assert_array_equal(joined.no_estimate, [False, True, False, True, False])
    np.testing.assert_array_equal(joined.theta, np.concatenate([a.theta, b.theta]))
    assert joined.run_s == 2.0 and joined.method == "hmc"
    assert (joined.reparam, joined.options, joined.gibbs, joined.sweeps) == (
        "albedo",
        opts,
        gibbs,
        4,
    )


def test_chunk_file_keeps_no_estimate_and_reparam(tmp_path):
    s = _samples(3, 0.0, [True, False, False], reparam="albedo", options=jp.HMCOptions())
    fp = fingerprint("first", np.arange(3), jp.HMCOptions(), 0, 3, None)
    store = open_pass(tmp_path, "first", fp)
    save_chunk(store, 0, s, 2.5)
    loaded = load_chunk(store, 0, 3, LABELS)
    assert loaded is not None
    back, run_s = loaded
    assert run_s == 2.5 and back.reparam == "albedo" and back.options is None
    np.testing.assert_array_equal(back.no_estimate, [True, False, False])
    np.testing.assert_array_equal(back.theta, s.theta)
    np.testing.assert_array_equal(back.stats["acceptance_rate"], s.stats["acceptance_rate"])
