"""Measured-BRDF readers on the shared data: documented counts, physical sanity, the
direction convention, and clear errors on corrupt or truncated copies."""

import re
from pathlib import Path

import numpy as np
import pytest

from jaxrefl.io import MeasuredBRDF, MeasuredDataError, read_cornell, read_curet

CORNELL = ("acryl_blue.astm", "krylon_blue.astm")


@pytest.fixture(scope="module")
def cornell_dir(shared_data) -> Path:
    return shared_data / "brdf" / "cornell"


@pytest.fixture(scope="module")
def curet_dir(shared_data) -> Path:
    return shared_data / "brdf" / "curet"


def _assert_unit_upper(m: MeasuredBRDF):
    for w in (m.wi, m.wo):
        assert w.shape == (len(m), 3) and w.dtype == np.float64
        np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=1e-12)
        assert np.all(w[:, 2] >= 0)


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


@pytest.mark.parametrize("name", CORNELL)
def test_cornell_counts_and_sanity(cornell_dir, name):
    path = cornell_dir / name
    num_points = int(re.search(r"^NUM_POINTS\s+(\d+)", path.read_text(), re.M).group(1))
    m = read_cornell(path)
    assert num_points == 1439 and len(m) == num_points
    assert m.values.shape == (num_points, 31)
    assert m.channels == tuple(f"{w}nm" for w in range(400, 701, 10))
    np.testing.assert_array_equal(m.wavelengths_nm, np.arange(400.0, 701.0, 10.0))
    assert m.meta["header"]["MEAS_NAME"] == "BRDF" and m.source == str(path)
    _assert_unit_upper(m)
    # Physical sanity: finite, non-negative (both files have no negative value), and
    # incidence 10..80 degrees as the data README says.
    assert np.all(np.isfinite(m.values)) and m.meta["n_negative"] == 0 == m.count_negative()
    theta_i = np.degrees(np.arccos(m.wi[:, 2]))
    # (angles are printed with 6 decimals in radians: 0.174533 rad = 10.0000035 degrees)
    np.testing.assert_allclose(np.unique(np.round(theta_i, 3)), np.arange(10.0, 81.0, 10.0))
    np.testing.assert_allclose(m.meta["angles"][:, 0], np.radians(theta_i), atol=1e-12)


@pytest.mark.parametrize("name", CORNELL)
def test_cornell_specular_peak_is_at_the_mirror_direction(cornell_dir, name):
    """The sign convention: no π shift. For every incidence the largest value is at the
    measured direction closest to reflect(wi) (within 4 degrees: the sampling grid), while
    a π-shifted convention would put it far from any mirror direction."""
    m = read_cornell(cornell_dir / name)
    mean = m.values.mean(axis=1)
    theta_i = np.round(np.degrees(np.arccos(m.wi[:, 2])))
    for t in np.unique(theta_i):
        rows = np.flatnonzero(theta_i == t)
        mirror = m.wi[rows] * [-1.0, -1.0, 1.0]
        off = _angle_deg(m.wo[rows], mirror)
        peak = np.argmax(mean[rows])
        assert peak == np.argmin(off) and off[peak] < 4.0, (t, off[peak], off.min())
        shifted = m.wo[rows[peak]] * [-1.0, -1.0, 1.0]  # the peak under a π shift of φs
        assert _angle_deg(shifted, mirror[peak]) > 2 * t - 5
        # ...and it is a real highlight, above the median of that incidence.
        assert mean[rows[peak]] > 1.3 * np.median(mean[rows])


def test_curet_counts_and_sanity(curet_dir):
    samples = read_curet(curet_dir / "abrdf.dat", curet_dir / "table.txt")
    assert isinstance(samples, list) and len(samples) == 61
    assert [s.meta["sample"] for s in samples] == list(range(1, 62))
    for s in samples:
        assert s.values.shape == (205, 1) and s.channels == ("mean_rgb",)
    m = samples[0]
    _assert_unit_upper(m)
    values = np.concatenate([s.values for s in samples])
    assert np.all(np.isfinite(values))
    # Negatives: 29 tiny ones (calibration offset plus noise on dark samples), recorded.
    assert sum(s.meta["n_negative"] for s in samples) == 29
    assert values.min() > -0.02
    # f_r in 1/sr: every sample's median is below the Lambertian bound 1/π.
    assert all(np.median(s.values) < 1 / np.pi for s in samples)
    # Geometry convention: lamp-camera angle is a multiple of 22.5° for every geometry.
    ang = _angle_deg(m.wi, m.wo)
    np.testing.assert_allclose(ang / 22.5, np.round(ang / 22.5), atol=1e-4)
    assert set(np.round(ang / 22.5).astype(int)) == set(range(1, 8))
    # The shiny sample 15 peaks at a mirror geometry.
    s15 = read_curet(curet_dir / "abrdf.dat", curet_dir / "table.txt", sample=15)
    peak = int(np.argmax(s15.values[:, 0]))
    assert _angle_deg(s15.wo[peak], s15.wi[peak] * [-1.0, -1.0, 1.0]) < 1e-3
    np.testing.assert_array_equal(s15.values, samples[14].values)


def test_curet_several_channel_files(curet_dir, tmp_path):
    # Three single-channel files (like rbrdf/gbrdf/bbrdf) read together as channels.
    src = (curet_dir / "abrdf.dat").read_text()
    paths = []
    for c in "rgb":
        p = tmp_path / f"{c}brdf.dat"
        p.write_text(src)
        paths.append(p)
    m = read_curet(paths, curet_dir / "table.txt", sample=3)
    assert m.channels == ("R", "G", "B") and m.values.shape == (205, 3)
    np.testing.assert_array_equal(m.values[:, 0], m.values[:, 2])


def _corrupt_copy(tmp_path, src: Path, name: str, edit) -> Path:
    lines = src.read_text().splitlines(keepends=True)
    out = tmp_path / name
    out.write_text("".join(edit(lines)))
    return out


def _replace(i, new):
    def edit(lines):
        lines = list(lines)
        lines[i] = new
        return lines

    return edit


@pytest.mark.parametrize(
    "name,edit,pattern",
    [
        (
            "rows.astm",
            lambda ls: ls[:-10],
            r"rows\.astm: row count mismatch: NUM_POINTS says 1439, found 1429",
        ),
        (
            "cut.astm",
            lambda ls: [*ls[:-1], ls[-1][:40]],
            r"cut\.astm, line 1461: wrong number of columns: \d+, expected 35",
        ),
        (
            "text.astm",
            _replace(30, "0.1,0.2,abc" + ",0.0" * 32 + "\n"),
            r"text\.astm, line 31: non-numeric value 'abc' in column 'theta_s'",
        ),
        (
            "novars.astm",
            lambda ls: [x for x in ls if not x.startswith("VARS")],
            r"novars\.astm, line 22: missing VARS",
        ),
        (
            "nonum.astm",
            lambda ls: [x for x in ls if not x.startswith("NUM_POINTS")],
            r"nonum\.astm: missing NUM_POINTS",
        ),
        (
            "bands.astm",
            _replace(20, "VARS theta_i,phi_i,theta_s,phi_s,400nm\n"),
            r"bands\.astm, line 23: wrong number of columns: 35, expected 5",
        ),
        (
            "angle.astm",
            _replace(22, "2.0" + ",0.0" * 34 + "\n"),
            r"angle\.astm, line 23: polar angle beyond",
        ),
        (
            "nan_angle.astm",
            _replace(22, "0.1,nan" + ",0.0" * 33 + "\n"),
            r"nan_angle\.astm, line 23: angle 'phi_i' is nan; angles must be finite",
        ),
    ],
)
def test_cornell_corrupt_files(cornell_dir, tmp_path, name, edit, pattern):
    path = _corrupt_copy(tmp_path, cornell_dir / "acryl_blue.astm", name, edit)
    with pytest.raises(MeasuredDataError, match=pattern) as info:
        read_cornell(path)
    assert isinstance(info.value, ValueError) and info.value.path == path


def test_cornell_binary_garbage(tmp_path):
    path = tmp_path / "garbage.astm"
    path.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(MeasuredDataError, match=r"garbage\.astm: not a text file"):
        read_cornell(path)


@pytest.mark.parametrize(
    "which,name,edit,pattern",
    [
        ("abrdf.dat", "short.dat", lambda ls: ls[:-3], r"short\.dat: 58 sample rows, expected 61"),
        (
            "abrdf.dat",
            "cols.dat",
            lambda ls: [*ls[:-1], ls[-1][:300]],
            r"cols\.dat, line 61: wrong number of columns: \d+, expected 206",
        ),
        (
            "abrdf.dat",
            "nan.dat",
            _replace(4, "5 " + "x.1 " * 205 + "\n"),
            r"nan\.dat, line 5: non-numeric value 'x\.1' in column 2",
        ),
        (
            "abrdf.dat",
            "dup.dat",
            _replace(4, "4" + "   0.1" * 205 + "\n"),
            r"dup\.dat, line 5: sample 4 appears twice",
        ),
        (
            "table.txt",
            "table_short.txt",
            lambda ls: ls[:-5],
            r"table_short\.txt: 200 geometry rows; the CURET table has 205",
        ),
        (
            "table.txt",
            "table_order.txt",
            _replace(9, "11 0.1 0.2 0.3 0.4\n"),
            r"table_order\.txt, line 10: geometry index 11, expected 10",
        ),
        (
            "table.txt",
            "table_cols.txt",
            _replace(9, "10 0.1 0.2 0.3\n"),
            r"table_cols\.txt, line 10: wrong number of columns: 4, expected 5",
        ),
        (
            "table.txt",
            "table_nan.txt",
            _replace(9, "10 0.1 nan 0.3 0.4\n"),
            r"table_nan\.txt, line 10: angle phi_v is nan; angles must be finite",
        ),
        (
            "abrdf.dat",
            "index_nan.dat",
            _replace(4, "nan" + "   0.1" * 205 + "\n"),
            r"index_nan\.dat, line 5: sample index nan, expected an integer",
        ),
    ],
)
def test_curet_corrupt_files(curet_dir, tmp_path, which, name, edit, pattern):
    bad = _corrupt_copy(tmp_path, curet_dir / which, name, edit)
    values = bad if which == "abrdf.dat" else curet_dir / "abrdf.dat"
    table = bad if which == "table.txt" else curet_dir / "table.txt"
    with pytest.raises(MeasuredDataError, match=pattern):
        read_curet(values, table)


def test_measured_container():
    n = 5
    wi = np.tile([0.0, 0.0, 1.0], (n, 1))
    wo = np.tile([0.6, 0.0, 0.8], (n, 1))
    wo[3] = [0.6, 0.0, -0.8]  # below the horizon
    values = np.arange(2.0 * n).reshape(n, 2)
    values[1, 0] = np.nan
    values[2, 1] = -0.1
    m = MeasuredBRDF(wi, wo, values, channels=("a", "b"), name="t")
    assert len(m) == 5 and m.n_channels == 2 and m.count_negative() == 1
    sel = m.select(np.array([True, False, True, False, False]))
    np.testing.assert_array_equal(sel.values, values[[0, 2]])
    v = m.mask_valid()
    assert len(v) == 3 and v.meta["dropped"] == {"non_finite": 1, "below_horizon": 1}
    v2 = m.mask_valid(drop_negative=True)
    assert len(v2) == 2 and v2.meta["dropped"]["negative"] == 1
    assert "dropped" not in m.meta  # the original is untouched
    assert m.select_channels(["b"]).values.shape == (5, 1)
    with pytest.raises(ValueError, match=r"3 channel names"):
        MeasuredBRDF(wi, wo, values, channels=("a", "b", "c"))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        MeasuredBRDF(wi[:, :2], wo, values, channels=("a", "b"))
