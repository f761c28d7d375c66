"""Photometric-stereo loaders: a synthetic capture written in the DiLiGenT layout (16-bit
PNGs read at full depth, Normal_gt.mat/.png), bad input with clear errors, and the real
UW psm spheres (gray sphere against its fitted ideal sphere, chrome-sphere calibration
against lights.txt)."""

from __future__ import annotations

import numpy as np
import pytest

import jaxrefl
from jaxrefl import ps
from jaxrefl.io import read_png, write_png


def _synthetic(h=24, w=28, k=12):
    _, n, m = ps.sphere_surface(h, w)
    lights = ps.spiral_lights(k, 50.0)
    e = np.linspace(0.6, 1.2, k)[:, None] * np.array([[1.0, 0.9, 0.8]])
    img = ps.render(
        jaxrefl.brdf.get("lambert"), {"albedo": np.array([0.6, 0.7, 0.8])}, n, m, lights, e
    )
    return img, lights, e, m, n


@pytest.fixture(scope="module")
def diligent(tmp_path_factory):
    img, lights, e, m, n = _synthetic()
    root = ps.save_diligent(tmp_path_factory.mktemp("dil") / "ballPNG", img, lights, e, m, n)
    return root, img, lights, e, m, n


def test_diligent_roundtrip_full_depth(diligent):
    root, img, lights, e, m, n = diligent
    cap = ps.load_diligent(root)
    assert cap.bit_depth == 16 and cap.images.shape == img.shape
    # Values survive at 16 bits (8 bits would leave errors up to 1/510).
    assert np.max(np.abs(cap.images - img)) <= 0.5 / 65535 + 1e-7
    np.testing.assert_allclose(cap.lights, lights, atol=1e-7)
    np.testing.assert_allclose(cap.intensities, e, atol=1e-7)
    assert np.array_equal(cap.mask, m)
    assert ps.angular_error(cap.normals_gt[m], n[m]).max() < 1e-6  # from Normal_gt.mat
    (root / "Normal_gt.mat").rename(root / "hidden.mat")
    try:
        png_gt = ps.load_diligent(root).normals_gt
    finally:
        (root / "hidden.mat").rename(root / "Normal_gt.mat")
    assert ps.angular_error(png_gt[m], n[m]).max() < 0.01  # 16-bit PNG quantisation
    a, bits = read_png(root / "001.png")
    assert bits == 16 and a.dtype == np.uint16


@pytest.mark.parametrize("method", ["ls", "robust"])
def test_methods_on_diligent_layout(diligent, method):
    root, *_ = diligent
    cap = ps.load_capture(root)
    maps = ps.solve_capture(cap, ps.METHODS[method]())
    ok = maps["status"] < jaxrefl.fit.Status.MASKED
    err = ps.angular_error(maps["normals"], cap.normals_gt)
    # Robust drops attached shadows; LS only on pixels lit in every image.
    lit = np.all(cap.images[..., 0] > 0, axis=0) & ok
    sel = lit if method == "ls" else ok
    assert sel.sum() > 100
    assert np.nanmax(err[sel]) < 0.5


def _copy(root, dst):
    import shutil

    return Path(shutil.copytree(root, dst))


from pathlib import Path  # noqa: E402


def test_bad_input_names_the_file(diligent, tmp_path):
    root, _, lights, _, m, _ = diligent
    # Images of different sizes.
    d = _copy(root, tmp_path / "size")
    write_png(d / "003.png", np.zeros((10, 10, 3), np.uint16))
    with pytest.raises(ValueError, match=r"003\.png.*one size"):
        ps.load_diligent(d)
    # Light count that does not match the images.
    d = _copy(root, tmp_path / "count")
    np.savetxt(d / "light_directions.txt", lights[:-1])
    with pytest.raises(ValueError, match=r"light_directions\.txt.*11 light directions for 12"):
        ps.load_diligent(d)
    # Zero-length light and a light below the horizon.
    d = _copy(root, tmp_path / "zero")
    bad = lights.copy()
    bad[2] = 0.0
    np.savetxt(d / "light_directions.txt", bad)
    with pytest.raises(ValueError, match=r"light 2 \(line 3\) has zero length"):
        ps.load_diligent(d)
    bad = lights.copy()
    bad[4, 2] = -0.2
    np.savetxt(d / "light_directions.txt", bad)
    with pytest.raises(ValueError, match=r"light 4 \(line 5\).*below the horizon"):
        ps.load_diligent(d)
    # A negative intensity is reported against the intensities file.
    d = _copy(root, tmp_path / "ints")
    ints = np.loadtxt(d / "light_intensities.txt", ndmin=2)
    ints[3, 1] = -1.0
    np.savetxt(d / "light_intensities.txt", ints)
    with pytest.raises(ps.PSInputError, match=r"light_intensities\.txt: light 3 \(line 4\)"):
        ps.load_diligent(d)
    # A truncated mask and a non-UTF-8 listing.
    d = _copy(root, tmp_path / "cut")
    (d / "mask.png").write_bytes((d / "mask.png").read_bytes()[:40])
    with pytest.raises(ValueError, match=r"mask\.png: cannot read image"):
        ps.load_diligent(d)
    (d / "filenames.txt").write_bytes(b"\xff\xfe001.png\n")
    with pytest.raises(ps.PSInputError, match=r"filenames\.txt: not a UTF-8 text file"):
        ps.load_diligent(d)
    # Empty mask.
    d = _copy(root, tmp_path / "mask")
    write_png(d / "mask.png", np.zeros(m.shape, np.uint8))
    with pytest.raises(ValueError, match=r"mask\.png.*empty"):
        ps.load_diligent(d)
    # 8-bit images where DiLiGenT has 16-bit ones.
    d = _copy(root, tmp_path / "eight")
    write_png(d / "001.png", np.zeros((*m.shape, 3), np.uint8))
    with pytest.raises(ValueError, match=r"001\.png.*8-bit PNG where DiLiGenT images are 16-bit"):
        ps.load_diligent(d)
    # Missing folder / file.
    with pytest.raises(FileNotFoundError):
        ps.load_capture(tmp_path / "nowhere")
    # A masked pixel with a status (not an error): an all-dark pixel inside the mask.
    cap = ps.load_diligent(root)
    cap.images[:, 12, 14] = 0.0
    cap.usable[:, 12, 14] = False
    maps = ps.solve_capture(cap, ps.LeastSquares())
    assert maps["status"][12, 14] == jaxrefl.fit.Status.MASKED
    assert np.all(np.isnan(maps["normals"][12, 14]))


def test_mat_reader_roundtrip(tmp_path):
    a = np.random.default_rng(0).normal(size=(5, 4, 3))
    for comp in (True, False):
        ps.write_mat(tmp_path / "x.mat", {"Normal_gt": a}, compress=comp)
        np.testing.assert_array_equal(ps.read_mat(tmp_path / "x.mat")["Normal_gt"], a)
    (tmp_path / "y.mat").write_bytes(b"not a mat file" * 20)
    with pytest.raises(ValueError, match="not a level-5 MAT file"):
        ps.read_mat(tmp_path / "y.mat")


# ----------------------------------------------------------------------- real UW data
@pytest.fixture(scope="module")
def uw(shared_data):
    return shared_data / "photometric_stereo" / "uw_psm"


def test_uw_gray_sphere_against_fitted_sphere(uw):
    cap = ps.load_uw(uw / "gray").downsample(3)
    assert cap.images.shape == (12, 114, 171, 3) and cap.bit_depth == 8
    means = {}
    for method in ("ls", "robust"):
        maps = ps.solve_capture(cap, ps.METHODS[method]())
        _, stats, circle = ps.sphere_error(maps["normals"], cap.mask)
        means[method] = stats
    # Measured (downsample 3): LS mean 5.5 / median 4.5 deg; robust about 1 deg better.
    assert means["ls"].mean < 6.5 and means["ls"].median < 5.5
    assert means["robust"].mean < means["ls"].mean
    assert means["robust"].median < 4.5
    assert abs(circle.radius - 108.3 / 3) < 1.5


def test_uw_chrome_calibration_against_lights_txt(uw):
    chrome = ps.load_uw(uw / "chrome").downsample(2)
    cal = ps.chrome_sphere_lights(chrome.images, chrome.mask)
    err = cal.error_deg(chrome.lights)
    # Measured: mean 3.0, max 8.4 deg at full and half resolution.
    assert err.mean() < 4.0 and err.max() < 10.0
    assert np.all(cal.std_deg > 0)
    gray = ps.load_uw(uw / "gray").downsample(2)
    lam = ps.lambertian_sphere_lights(gray.images, gray.mask)
    # The two independent calibrations agree with each other better than with lights.txt.
    assert lam.error_deg(cal.directions).mean() < err.mean()


def test_uw_bad_lights_file(uw, tmp_path):
    lights = (uw / "lights.txt").read_text().splitlines()
    (tmp_path / "l.txt").write_text("\n".join(["11", *lights[1:]]) + "\n")
    with pytest.raises(ValueError, match=r"l\.txt.*says 11 lights but 12 follow"):
        ps.load_uw(uw / "gray", lights=tmp_path / "l.txt")
    (tmp_path / "l.txt").write_text("\n".join(["11", *lights[1:-1]]) + "\n")
    with pytest.raises(ValueError, match=r"11 light directions for 12 images"):
        ps.load_uw(uw / "gray", lights=tmp_path / "l.txt")
