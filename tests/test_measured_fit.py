"""Fitting analytic models to measured BRDFs (jaxrefl.measured): recovery of known models
from synthetic samples and a MERL file, the Cornell data as RGB and per band, CURET."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import fit
from jaxrefl import measured as jm
from jaxrefl.brdf import MERL, Ward
from jaxrefl.io import MeasuredBRDF, write_merl
from jaxrefl.measured._data import detect_format
from jaxrefl.measured._metrics import sample_weights


def _gonio(k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)

    def hemi():
        u = rng.uniform(np.cos(np.radians(75.0)), 1.0, k)
        phi = rng.uniform(0.0, 2 * np.pi, k)
        s = np.sqrt(1 - u * u)
        return np.stack([s * np.cos(phi), s * np.sin(phi), u], -1)

    wi = hemi()
    wo = hemi()
    # A third of the views near the mirror direction, so the highlight is sampled.
    wo[: k // 3] = wi[: k // 3] * np.array([-1.0, -1.0, 1.0]) + 0.05 * rng.normal(size=(k // 3, 3))
    wo[:, 2] = np.abs(wo[:, 2]) + 0.05
    return wi, wo / np.linalg.norm(wo, axis=-1, keepdims=True)


def test_default_model_set():
    assert jm.DEFAULT_MODELS == (
        "lambert",
        "blinn_phong",
        "ward",
        "beckmann",
        "ggx",
        "lafortune_1",
        "lafortune_2",
        "lafortune_3",
    )
    sizes = {n: len(jm.build_model(n).params) for n in jm.DEFAULT_MODELS}
    assert sizes["lambert"] == 1 and sizes["lafortune_3"] == 2 and sizes["ward"] == 3
    assert jm.build_model("lafortune_3").num_lobes == 3
    assert jm.build_model("blinn_phong").reciprocal  # the normalised form
    with pytest.raises(ValueError, match="unknown model"):
        jm.build_model("phong_2")


def test_recovers_a_known_ward_brdf():
    truth = {"albedo": np.array([0.4, 0.3, 0.2]), "specular": np.array([0.05] * 3), "alpha": 0.08}
    # K = 1439, the number of Cornell samples within 80 degrees: the Ward fit below and the
    # one of test_cornell_as_rgb_and_per_band share one compilation.
    wi, wo = _gonio(1439, seed=1)
    f = np.asarray(Ward().eval({k: jnp.asarray(v) for k, v in truth.items()}, wi, wo))
    m = MeasuredBRDF(wi, wo, f, ("R", "G", "B"), name="synthetic ward")
    rep = jm.fit_brdf(m, ["lambert", "ward"], config=fit.FitConfig(dtype=np.float32))
    ward, lam = rep.fits["ward"], rep.fits["lambert"]
    assert ward.dtype == "float32" and ward.retry is None
    np.testing.assert_allclose(ward.params["alpha"], 0.08, rtol=2e-3)
    np.testing.assert_allclose(ward.params["albedo"], truth["albedo"], rtol=2e-3)
    np.testing.assert_allclose(ward.params["specular"], truth["specular"], rtol=5e-3)
    # An exact model fits to float32 round-off; Lambert cannot explain the highlight.
    assert ward.metrics["relative_l2"] < 1e-3 < 0.1 < lam.metrics["relative_l2"]
    assert ward.metrics["cosine_weighted_l2"] < 1e-3 * lam.metrics["cosine_weighted_l2"]
    assert rep.best() == "ward" and (ward.n_params, lam.n_params) == (7, 3)
    assert ward.fit_time_s > 0 and ward.compile_time_s >= 0
    d = json.loads(json.dumps(rep.to_dict()))  # JSON-ready
    assert d["models"]["ward"]["params"]["alpha"] == pytest.approx(0.08, rel=2e-3)
    assert set(d["models"]["ward"]["metrics"]) == set(jm.METRICS)
    assert d["n_samples"] == len(m) and d["settings"]["max_theta_deg"] == 80.0
    assert "| ward | 7 |" in rep.table()


def test_cornell_as_rgb_and_per_band(shared_data):
    m = jm.load_measured(shared_data / "brdf/cornell/acryl_blue.astm")
    assert m.wavelengths_nm is not None and m.n_channels == 31
    # A constant spectrum is the same f_r in every channel (white-normalised conversion).
    flat = MeasuredBRDF(m.wi[:5], m.wo[:5], np.full((5, 31), 0.7), m.channels,
                        wavelengths_nm=m.wavelengths_nm)  # fmt: skip
    np.testing.assert_allclose(jm.to_rgb(flat).values, 0.7, rtol=1e-9)
    rgb = jm.to_rgb(m, "D65")
    assert rgb.channels == ("R", "G", "B") and rgb.meta["color"]["illuminant"] == "D65"
    assert np.all(rgb.values[:, 2] >= rgb.values[:, 0] - 1e-3)  # blue acrylic

    rep = jm.fit_brdf(m, ["ward"])
    ward = rep.fits["ward"]
    assert rep.settings["illuminant"] == "D65" and len(rep.measured) == 1439
    # Measured on this file: a sharp highlight (alpha ~0.014), cos-weighted L2 0.050 /sr
    # against 0.237 for Lambert (CLI run), relative L2 0.19.
    assert 0.005 < float(ward.params["alpha"]) < 0.05
    assert ward.metrics["cosine_weighted_l2"] < 0.1 and ward.metrics["relative_l2"] < 0.4

    # Per band: three bands, each its own problem with its own albedo.
    bands = m.select_channels(["450nm", "550nm", "650nm"])
    rb = jm.fit_brdf(
        bands,
        ["lambert"],
        options=jm.MeasuredOptions(retry_float64=False, spectral="bands"),
        timing=False,
    )
    lam = rb.fits["lambert"]
    assert lam.channels == "separate" and lam.params["albedo"].shape == (3,)
    assert lam.n_params == 3 and rb.settings["illuminant"] is None
    assert lam.params["albedo"][0] > 2 * lam.params["albedo"][2]  # blue reflects more
    assert np.isfinite(lam.metrics["log_l2"])


def test_merl_file_from_an_analytic_model(tmp_path):
    model = jm.build_model("cook_torrance_ggx")  # an alias of ggx
    truth = {
        "albedo": jnp.asarray([0.3, 0.2, 0.1]),
        "specular": jnp.asarray([0.04, 0.05, 0.06]),
        "alpha": jnp.asarray(0.12),
    }
    path = tmp_path / "ggx.binary"
    write_merl(path, MERL.from_brdf(model, truth, dtype=jnp.float64))
    m = jm.load_measured(path, merl_samples=1500, seed=3)
    assert len(m) == 1500 and m.meta["format"] == "MERL binary"
    w = sample_weights(m)
    assert w.std() > 0.1  # cells of unequal solid angle
    cfg = fit.FitConfig(dtype=np.float64)
    rep = jm.fit_brdf(m, ["ggx"], config=cfg, timing=False)
    ct = rep.fits["ggx"]
    # Cell centres are stored exactly, so the fit recovers the model.
    for name, v in truth.items():
        np.testing.assert_allclose(ct.params[name], np.asarray(v), rtol=1e-5)
    assert ct.metrics["cosine_weighted_l2"] < 1e-6
    assert rep.settings["spectral"] is None and ct.dtype == "float64"


def test_curet_needs_a_sample(shared_data):
    path = shared_data / "brdf/curet/abrdf.dat"
    assert detect_format(path) == "curet"
    with pytest.raises(ValueError, match="choose one"):
        jm.load_measured(path)
    m = jm.load_measured(path, curet_sample=15)
    assert len(m) == 205 and m.channels == ("mean_rgb",)
    assert len(jm.restrict(m)) < 205  # grazing geometries left out
    with pytest.raises(FileNotFoundError):
        jm.load_measured(path, curet_sample=15, curet_table=path.with_name("missing.txt"))
