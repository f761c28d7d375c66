"""The family of synthetic flash captures (``benchmarks/capture_family.py``): what it writes
reads back through :func:`jaxrefl.io.load_capture` in every layout, the images are the
rendered ones (exactly in EXR, within the 8-bit quantisation in the public layouts), the
geometry is the true camera with the flash at the lens unless asked, the truth maps follow
the fit's conventions, and the family spans the ranges it claims."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import svbrdf
from jaxrefl.io import ObsStatus, load_capture

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import capture_family as cf

SIZE = 16


def _tiny(name: str) -> cf.FamilyMember:
    return dataclasses.replace(next(m for m in cf.FAMILY if m.name == name), size=SIZE)


@pytest.fixture(scope="module")
def rendered() -> cf.RenderedMember:
    # a coloured metal on part of the surface, the flash off the lens, 16 photos
    return cf.render_member(_tiny("copper_inlay"))


@pytest.mark.parametrize("layout", cf.LAYOUTS)
def test_written_capture_loads_with_rendered_images_and_geometry(rendered, layout, tmp_path):
    r = rendered
    m = r.member
    cap = load_capture(cf.write_member(r, tmp_path / layout, layout))
    assert cap.layout == layout
    assert cap.shape == (m.photos, SIZE, SIZE, 3)
    np.testing.assert_allclose(cap.camera_pos, r.camera_pos, rtol=0, atol=1e-12)
    # the flash is written at the lens, though the true one is off it
    np.testing.assert_allclose(cap.light_pos, r.camera_pos, rtol=0, atol=1e-12)
    offset = np.linalg.norm(r.light_pos - r.camera_pos, axis=1)
    np.testing.assert_allclose(offset, m.flash_offset_cm, rtol=1e-12)
    np.testing.assert_allclose(cap.light_power, r.light_power, rtol=1e-12)
    assert cap.side == pytest.approx(m.side_cm, rel=1e-12)
    saturated = cap.status == ObsStatus.SATURATED
    assert saturated.any()  # the metal's highlights clip, as in real photos
    if layout == "generic":  # float32 EXR: the rendered values, saturated at 1
        np.testing.assert_array_equal(cap.images, r.images)
        np.testing.assert_array_equal(saturated, r.images >= 1.0)
    else:  # 8-bit value^(1/2.2): within half a code, saturated at the top code
        top = np.rint(r.images ** (1 / cf.GAMMA) * 255) == 255
        np.testing.assert_array_equal(saturated, top)
        enc = np.abs(cap.images ** (1 / cf.GAMMA) - r.images ** (1 / cf.GAMMA))
        assert enc.max() <= 0.5 / 255 + 1e-5
        assert enc.max() > 0  # the quantisation is there to see
    truth = np.load(tmp_path / layout / "truth.npz")
    want = {**r.truth, "light_pos": r.light_pos, "camera_pos": r.camera_pos}
    for key in ("albedo", "specular", "alpha", "roughness", "metal", "light_pos", "camera_pos"):
        np.testing.assert_array_equal(truth[key], want[key])
    assert json.loads((tmp_path / layout / "member.json").read_text())["name"] == m.name


def test_true_light_option_writes_the_offset_flash(rendered, tmp_path):
    cap = load_capture(cf.write_member(rendered, tmp_path, "generic", true_light=True))
    np.testing.assert_allclose(cap.light_pos, rendered.light_pos, rtol=0, atol=1e-12)
    assert np.all(np.linalg.norm(cap.light_pos - cap.camera_pos, axis=1) > 0.5)


def test_images_are_the_fit_model_of_the_truth_under_the_true_geometry(rendered):
    """The radiance is the ``ggx_rgb`` prediction of the true maps with the true (offset)
    flash (the model's convention: prediction = f_r * irradiance * cos_i), not with the
    flash at the lens; the images are that plus the stated noise, clipped to [0, 1]."""
    r = rendered
    model, _space = svbrdf.capture_model("ggx_rgb")
    params = {n: jnp.asarray(r.truth[n]) for n in model.param_names}

    def predict(cap):
        g = cap.per_pixel_geometry(dtype=np.float64)
        f = np.asarray(model.eval(params, jnp.asarray(g["wi"]), jnp.asarray(g["wo"])))
        return f * g["irradiance"] * g["cos_i"][..., None]

    true = predict(r.capture(true_light=True))
    np.testing.assert_allclose(r.radiance, true, rtol=2e-4, atol=1e-6)
    at_lens = predict(r.capture())
    assert np.max(np.abs(at_lens - true) / true) > 0.01  # the offset changes the photos
    unclipped = (r.images > 0) & (r.images < 1)
    z = (r.images - r.radiance) / (r.member.noise * (r.radiance + cf.NOISE_FLOOR))
    assert abs(np.mean(z[unclipped])) < 0.1
    assert np.std(z[unclipped]) == pytest.approx(1.0, abs=0.1)


def test_truth_maps_follow_the_members_ranges_and_the_seed(rendered):
    t = rendered.truth
    m = rendered.member
    assert t["albedo"].shape == t["specular"].shape == (SIZE, SIZE, 3)
    assert t["alpha"].shape == t["roughness"].shape == t["metal"].shape == (SIZE, SIZE)
    assert m.alpha_range[0] <= t["alpha"].min() and t["alpha"].max() <= m.alpha_range[1]
    np.testing.assert_allclose(t["roughness"] ** 2, t["alpha"])
    metal = t["metal"] == 1.0
    assert metal.any() and (t["metal"] == 0.0).any()  # an inlay: metal on part of it
    np.testing.assert_allclose(t["albedo"][metal], cf.METAL_ALBEDO)
    f0 = t["specular"][metal]
    assert np.all(f0 <= np.asarray(m.metal)) and np.all(f0[:, 0] > f0[:, 2])  # coloured
    again = cf.render_member(m)
    np.testing.assert_array_equal(again.images, rendered.images)
    other = cf.render_member(dataclasses.replace(m, seed=m.seed + 1))
    assert not np.array_equal(other.truth["alpha"], t["alpha"])


def test_a_member_is_one_material_at_any_size():
    m = _tiny("grey_gloss")
    small = cf.render_member(m).truth["alpha"]
    big = cf.render_member(dataclasses.replace(m, size=2 * SIZE)).truth["alpha"]
    # the fields are smooth: a 2x2 block of the larger map averages to the smaller's pixel
    pooled = big.reshape(SIZE, 2, SIZE, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(pooled, small, rtol=0.05)


def test_family_spans_the_stated_ranges():
    fam = cf.FAMILY
    assert len(fam) >= 6 and len({m.name for m in fam}) == len(fam)
    assert min(m.alpha_range[0] for m in fam) <= 0.02
    assert max(m.alpha_range[1] for m in fam) >= 0.7
    assert any(m.metal is not None and max(m.metal) >= 0.85 for m in fam)
    assert any(m.metal is None and m.f0 == (0.04, 0.04) for m in fam)
    offsets = {m.flash_offset_cm for m in fam}
    assert 0.0 in offsets and max(offsets) >= 1.5
    noise = [m.noise for m in fam]
    assert min(noise) <= 0.005 and max(noise) >= 0.03
    photos = {m.photos for m in fam}
    assert {5, 16} <= photos
    sizes = {m.size for m in fam}
    assert min(sizes) <= 64 and max(sizes) >= 256
    assert any(m.tiles == 0 for m in fam) and any(m.tiles > 0 for m in fam)
