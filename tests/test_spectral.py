"""Spectral utilities: IOR tables, colour matching, spectrum -> RGB, metal colours."""

import shutil

import numpy as np
import pytest

from jaxrefl.brdf._fresnel import fresnel_conductor
from jaxrefl.spectral import IOR, cie_xyz_cmf, load_ior, spectrum_to_rgb

# Normal-incidence reflectance of metals in linear sRGB, computed spectrally from measured
# data: Real-Time Rendering, 4th ed. (Akenine-Moeller et al. 2018), Table 9.2 (N. Hoffman).
RTR4_F0 = {
    "Au": (1.000, 0.782, 0.344),
    "Ag": (0.972, 0.960, 0.915),
    "Cu": (0.955, 0.638, 0.538),
    "Al": (0.913, 0.922, 0.924),
}


@pytest.fixture(scope="module")
def ior_dir(shared_data):
    return shared_data / "ior"


def spectral_f0_rgb(ior):
    lam = np.arange(380.0, 781.0, 5.0)
    eta, k = ior.at(lam)
    return np.asarray(spectrum_to_rgb(lam, np.asarray(fresnel_conductor(1.0, eta, k))))


def test_load_ior_gold(ior_dir):
    au = load_ior("Au", ior_dir)
    assert isinstance(au, IOR) and au.name == "Au" and "luxpop" in au.source
    # The header says "Lambda (A)" but the numbers are nm (shared/data/README.md).
    assert 290 < au.wavelengths[0] < 310 and 880 < au.wavelengths[-1] < 890
    assert au.eta.shape == au.k.shape == au.wavelengths.shape
    # Gold at 550 nm: n ~ 0.35-0.43, k ~ 2.4-2.7 (Palik's handbook; Johnson & Christy 1972).
    eta, k = au.at(550.0)
    assert 0.3 < float(eta) < 0.45 and 2.3 < float(k) < 2.8
    # Exact at a tabulated wavelength; the same files load by path prefix and by file path.
    np.testing.assert_allclose(au.at(au.wavelengths[10]), (au.eta[10], au.k[10]))
    for ref in (ior_dir / "Au", ior_dir / "Au.k.spd", str(ior_dir / "Au.eta.spd")):
        np.testing.assert_array_equal(load_ior(ref).eta, au.eta)


def test_interpolation_refuses_extrapolation(ior_dir):
    ag = load_ior("Ag", ior_dir)
    with pytest.raises(ValueError, match="leave the measured range"):
        ag.at([250.0, 500.0])
    eta, k = ag.at([250.0, 2000.0], clamp=True)
    np.testing.assert_array_equal(eta, ag.eta[[0, -1]])
    np.testing.assert_array_equal(k, ag.k[[0, -1]])


def test_corrupt_files_give_clear_errors(ior_dir, tmp_path):
    def case(name, eta_text=None, k_text=None):
        for part, text in (("eta", eta_text), ("k", k_text)):
            dst = tmp_path / f"{name}.{part}.spd"
            if text is None:
                shutil.copy(ior_dir / f"Au.{part}.spd", dst)
            else:
                dst.write_text(text)
        return tmp_path / f"{name}.eta.spd", tmp_path / f"{name}.k.spd"

    good = (ior_dir / "Au.eta.spd").read_text()
    lines = good.splitlines()
    cases = {
        "truncated": ("\n".join(lines[:-1]) + "\n885.60", "expected two numbers"),
        "garbage": (good.replace("1.812000", "1.8x2"), "expected two numbers"),
        "nonmono": (good.replace("302.400421", "298.0"), "increase strictly"),
        "negative": (good.replace("1.812000", "-1.812"), ">= 0"),
        "empty": ("# nothing here\n", "at least two data rows"),
        "nan": (good.replace("1.812000", "nan"), "non-finite"),
    }
    for name, (text, msg) in cases.items():
        eta_path, _ = case(name, eta_text=text)
        with pytest.raises(ValueError, match=msg) as err:
            load_ior(name, tmp_path)
        assert str(eta_path) in str(err.value), err.value
    # Grids that differ between the eta and k files (k truncated by whole rows).
    eta_path, k_path = case("grid", k_text="\n".join(lines[:-3]) + "\n")
    with pytest.raises(ValueError, match="different wavelength grids") as err:
        load_ior("grid", tmp_path)
    assert str(k_path) in str(err.value)
    with pytest.raises(FileNotFoundError, match="Au"):
        load_ior("Unobtainium", ior_dir)


def test_angstrom_file_is_converted(ior_dir, tmp_path):
    for part in ("eta", "k"):
        rows = np.loadtxt(ior_dir / f"Au.{part}.spd", comments="#")
        rows[:, 0] *= 10.0
        text = "# ;    Lambda (A)            n            k\n"
        text += "\n".join(f"{a:.6f} {b:.6f}" for a, b in rows)
        (tmp_path / f"AuA.{part}.spd").write_text(text)
    np.testing.assert_allclose(
        load_ior("AuA", tmp_path).wavelengths, load_ior("Au", ior_dir).wavelengths, rtol=1e-9
    )


def test_colour_matching_fit_and_white_point():
    lam = np.arange(360.0, 831.0, 1.0)
    cmf = cie_xyz_cmf(lam)
    # CIE 1931: y-bar peaks at 555 nm with value 1; the three integrals are equal (106.86)
    # for an equal-energy spectrum (CIE 15:2004). The fit reproduces both to ~1%.
    assert 550 <= lam[np.argmax(cmf[:, 1])] <= 560
    assert cmf[:, 1].max() == pytest.approx(1.0, abs=0.01)
    np.testing.assert_allclose(cmf.sum(axis=0), 106.86, rtol=0.015)
    for illum in ("E", "D65"):
        for grid in (np.arange(400.0, 701.0, 10.0), np.arange(380.0, 781.0, 5.0)):
            rgb = spectrum_to_rgb(grid, np.ones((2, grid.size)), illuminant=illum)
            np.testing.assert_allclose(rgb, 1.0, rtol=1e-12)
    # A red, a green and a blue band land in their channels.
    lam = np.arange(400.0, 701.0, 10.0)
    bands = np.stack([(lam >= 600), (lam >= 500) & (lam < 570), (lam < 480)]).astype(float)
    rgb = np.asarray(spectrum_to_rgb(lam, bands))
    assert np.all(np.argmax(rgb, axis=1) == [0, 1, 2])
    with pytest.raises(ValueError, match=r"380\.\.780"):
        spectrum_to_rgb(np.arange(300.0, 701.0, 10.0), np.ones(41))


def test_metal_colours_against_literature(ior_dir):
    for name, ref in RTR4_F0.items():
        rgb = spectral_f0_rgb(load_ior(name, ior_dir))
        # Gold lies outside the sRGB gamut (R > 1 before clipping); compare G and B there.
        cmp = slice(1, 3) if name == "Au" else slice(0, 3)
        np.testing.assert_allclose(rgb[cmp], np.asarray(ref)[cmp], atol=0.02, err_msg=name)
    au = spectral_f0_rgb(load_ior("Au", ior_dir))
    ag = spectral_f0_rgb(load_ior("Ag", ior_dir))
    assert au[0] > au[1] > au[2] and au[0] > 0.95  # yellow
    assert ag.min() > 0.9 and ag.max() - ag.min() < 0.07  # bright, near neutral


def test_ior_to_rgb_approximates_spectral_reflectance(ior_dir):
    for name in ("Au", "Ag", "Cu", "Al", "Cr"):
        ior = load_ior(name, ior_dir)
        spectral = spectral_f0_rgb(ior)
        for method in ("cie", "primaries"):
            eta, k = ior.to_rgb(method)
            assert eta.shape == k.shape == (3,) and np.all(eta > 0) and np.all(k > 0)
            f0 = np.asarray(fresnel_conductor(1.0, eta, k))
            np.testing.assert_allclose(f0, spectral, atol=0.06, err_msg=(name, method))
    eta, k = load_ior("Au", ior_dir).to_rgb()
    f0 = np.asarray(fresnel_conductor(1.0, eta, k))
    assert f0[0] > f0[1] > f0[2]
    # A constant spectrum keeps its value under the CIE projection.
    flat = IOR("flat", np.array([300.0, 900.0]), np.full(2, 1.5), np.full(2, 2.0), "test")
    np.testing.assert_allclose(np.concatenate(flat.to_rgb()), [1.5] * 3 + [2.0] * 3, rtol=1e-12)
