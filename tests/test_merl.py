"""MERL tabulated BRDF: BRDFRead.cpp index mapping, file round trip, lookups, errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl.brdf._base import BRDF
from jaxrefl.brdf._lambert import Lambert
from jaxrefl.brdf._merl import MERL, MERL_SCALE, MERL_SHAPE
from jaxrefl.brdf._rusinkiewicz import to_half_diff
from jaxrefl.io import MeasuredDataError, merl_to_measured, read_merl, write_merl

FILE_BYTES = 12 + 8 * 3 * 90 * 90 * 180
ALBEDO = np.array([0.2, 0.4, 0.6])


class HalfDiffLobe(BRDF):
    """Smooth, reciprocal, isotropic test lobe in half/difference angles (no parameters):
    f = c * exp(-θh² / 0.1) * (1 + 0.5 cos 2φd) * (1 + θd), c = (1, 2, 3)."""

    @property
    def params(self):
        return ()

    def _eval(self, p, wi, wo):
        th, _, td, pd = to_half_diff(wi, wo)
        g = jnp.exp(-(th**2) / 0.1) * (1 + 0.5 * jnp.cos(2 * pd)) * (1 + td)
        return jnp.stack([g, 2 * g, 3 * g], axis=-1)


def _brdfread_index(theta_h, theta_d, phi_d):
    """Transcription of BRDFRead.cpp theta_half_index, theta_diff_index, phi_diff_index."""
    out = []
    for h, d, p in zip(theta_h, theta_d, phi_d, strict=True):
        if h <= 0.0:
            i = 0
        else:
            i = min(max(int(np.sqrt((h / (np.pi / 2.0)) * 90 * 90)), 0), 89)
        j = int(d / (np.pi * 0.5) * 90)
        j = 0 if j < 0 else (j if j < 89 else 89)
        if p < 0.0:
            p += np.pi
        k = int(p / np.pi * 360 / 2)
        k = 0 if k < 0 else (k if k < 179 else 179)
        out.append((i, j, k))
    return np.array(out)


def _upper(rng, n):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 1e-3
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@eqx.filter_jit
def _f(m, wi, wo):
    """m.eval({}, wi, wo) compiled once per model structure (eager dispatch is slow)."""
    return m.eval({}, wi, wo)


_valid = eqx.filter_jit(lambda m, wi, wo: m.valid(wi, wo))
_index = eqx.filter_jit(lambda m, wi, wo: m.cell_index(wi, wo))


@pytest.fixture(scope="module")
def lambert_file(tmp_path_factory):
    m = MERL.from_brdf(Lambert(), {"albedo": jnp.asarray(ALBEDO)})
    path = tmp_path_factory.mktemp("merl") / "lambert.binary"
    write_merl(path, m)
    return path, np.asarray(m.table)


@pytest.fixture(scope="module")
def lobe():
    return MERL.from_brdf(HalfDiffLobe(), {})


def test_file_layout_and_round_trip(lambert_file, tmp_path):
    path, table = lambert_file
    raw_bytes = path.read_bytes()
    assert len(raw_bytes) == FILE_BYTES
    assert np.frombuffer(raw_bytes[:12], "<i4").tolist() == [90, 90, 180]
    raw = np.frombuffer(raw_bytes[12:], "<f8").reshape(MERL_SHAPE)
    # Channel-major, raw = f_r / scale: the Lambert cell (0, 0, 0) of each channel.
    np.testing.assert_allclose(raw[:, 0, 0, 0], ALBEDO / np.pi / np.array(MERL_SCALE), rtol=1e-14)
    m = read_merl(path)
    assert m.table.shape == MERL_SHAPE and m.params == () and m.reciprocal
    np.testing.assert_array_max_ulp(np.asarray(m.table), table, maxulp=1)
    # Writing what was read gives the same file up to 1 ulp per value.
    write_merl(tmp_path / "again.binary", m)
    raw2 = np.frombuffer((tmp_path / "again.binary").read_bytes()[12:], "<f8")
    np.testing.assert_array_max_ulp(raw2, raw.ravel(), maxulp=2)
    # Missing cells (centre below the horizon) are stored negative, about a quarter.
    frac_missing = float(np.mean(table[0] < 0))
    assert 0.15 < frac_missing < 0.35


def test_index_mapping_matches_brdfread():
    rng = np.random.default_rng(3)
    wi, wo = _upper(rng, 3000), _upper(rng, 3000)
    # Include exact boundaries: θh = 0, θd = 0, φd = 0 and ±π, grazing.
    wi[0], wo[0] = [0, 0, 1], [0, 0, 1]
    wi[1], wo[1] = [0.6, 0, 0.8], [-0.6, 0, 0.8]
    wi[2], wo[2] = [0.6, 0, 0.8], [0.6, 0, 0.8]
    wi[3], wo[3] = [1e-9, 0, 1.0], [-1.0, 0, 1e-9]
    m = MERL(jnp.zeros(MERL_SHAPE))
    ours = np.stack([np.asarray(a) for a in m.cell_index(jnp.asarray(wi), jnp.asarray(wo))], -1)
    th, _, td, pd = (np.asarray(a) for a in to_half_diff(jnp.asarray(wi), jnp.asarray(wo)))
    np.testing.assert_array_equal(ours, _brdfread_index(th, td, pd))
    assert ours[:, 0].max() > 80 and ours[:, 2].min() == 0 and ours[:, 2].max() == 179


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_cell_centres_map_to_their_cell(dtype):
    wi, wo = MERL.cell_directions(dtype)
    m = MERL(jnp.zeros(MERL_SHAPE))
    i, j, k = _index(m, wi, wo)
    grid = np.meshgrid(np.arange(90), np.arange(90), np.arange(180), indexing="ij")
    for got, want in zip((i, j, k), grid, strict=True):
        np.testing.assert_array_equal(np.asarray(got), want)


@pytest.mark.parametrize("interpolation", ["nearest", "trilinear"])
def test_lambert_lookup_is_albedo_over_pi(lambert_file, interpolation):
    m = read_merl(lambert_file[0], interpolation=interpolation)
    rng = np.random.default_rng(4)
    wi, wo = jnp.asarray(_upper(rng, 5000)), jnp.asarray(_upper(rng, 5000))
    f = np.asarray(_f(m, wi, wo))
    valid = np.asarray(_valid(m, wi, wo))
    assert f.shape == (5000, 3)
    assert valid.mean() > 0.9  # missing cells are the grazing ones only
    np.testing.assert_allclose(
        f[valid], np.broadcast_to(ALBEDO / np.pi, (valid.sum(), 3)), rtol=1e-12
    )
    assert np.all(f >= 0)  # missing cells read as 0, never negative or NaN
    if interpolation == "nearest":
        assert np.all(f[~valid] == 0)


def test_lobe_lookup(lobe):
    analytic = HalfDiffLobe()
    # At cell centres the lookup returns the tabulated analytic value exactly.
    wi, wo = MERL.cell_directions()
    sl = (slice(None, None, 7), slice(None, None, 5), slice(None, None, 3))
    wi, wo = wi[sl], wo[sl]
    ok = np.asarray(_valid(lobe, wi, wo))
    for interp in ("nearest", "trilinear"):
        m = MERL(lobe.table, interpolation=interp)
        np.testing.assert_allclose(
            np.asarray(_f(m, wi, wo))[ok], np.asarray(_f(analytic, wi, wo))[ok], rtol=1e-12
        )
    # Elsewhere: nearest = analytic value at the centre of the BRDFRead cell; trilinear is
    # much closer to the analytic lobe than nearest (the function is smooth).
    rng = np.random.default_rng(5)
    wi, wo = jnp.asarray(_upper(rng, 4000)), jnp.asarray(_upper(rng, 4000))
    ok = np.asarray(_valid(lobe, wi, wo))
    i, j, k = (np.asarray(a) for a in _index(lobe, wi, wo))
    th_c = ((i + 0.5) / 90) ** 2 * np.pi / 2
    td_c = (j + 0.5) / 90 * np.pi / 2
    pd_c = (k + 0.5) / 180 * np.pi
    g_c = np.exp(-(th_c**2) / 0.1) * (1 + 0.5 * np.cos(2 * pd_c)) * (1 + td_c)
    f_near = np.asarray(_f(lobe, wi, wo))
    np.testing.assert_allclose(f_near[ok], g_c[ok, None] * [1.0, 2.0, 3.0], rtol=1e-12)
    truth = np.asarray(_f(analytic, wi, wo))
    f_tri = np.asarray(_f(MERL(lobe.table, interpolation="trilinear"), wi, wo))
    inner = ok & (np.asarray(to_half_diff(wi, wo)[2]) < 1.0)  # away from missing cells
    err_near = np.abs(f_near - truth)[inner].max()
    err_tri = np.abs(f_tri - truth)[inner].max()
    assert err_tri < 0.1 * err_near and err_tri < 5e-4 * truth.max()


def test_reciprocity_and_isotropy(lobe):
    rng = np.random.default_rng(6)
    wi, wo = _upper(rng, 3000), _upper(rng, 3000)
    for interp in ("nearest", "trilinear"):
        m = MERL(lobe.table, interpolation=interp)
        f = np.asarray(_f(m, jnp.asarray(wi), jnp.asarray(wo)))
        f_swap = np.asarray(_f(m, jnp.asarray(wo), jnp.asarray(wi)))
        # Swapping moves φd by exactly π up to round-off, which flips a cell boundary in
        # (at most) a handful of samples for nearest lookup.
        n_diff = np.sum(np.any(np.abs(f - f_swap) > 1e-12 * np.abs(f).max(), axis=1))
        assert n_diff <= (3 if interp == "nearest" else 0)
        np.testing.assert_allclose(f, f_swap, atol=1e-9) if interp == "trilinear" else None
        # Rotating both directions about the normal leaves f unchanged (φh is ignored).
        c, s = np.cos(1.1), np.sin(1.1)
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        f_rot = np.asarray(_f(m, jnp.asarray(wi @ rot.T), jnp.asarray(wo @ rot.T)))
        n_rot = np.sum(np.any(np.abs(f - f_rot) > 1e-9 * np.abs(f).max(), axis=1))
        assert n_rot <= 3


@eqx.filter_jit
def _eval_valid_grad(m, wi, wo):
    f = m.eval({}, wi, wo)
    g = jax.grad(lambda a, b: m.eval({}, a, b).sum(), argnums=(0, 1))(wi, wo)
    return f, m.valid(wi, wo), m.cell_index(wi, wo)[0], g


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_missing_cells_jit_and_gradients(lobe, dtype):
    table = np.asarray(lobe.table).copy()
    table[:, 16] = -1.0 * np.asarray(MERL_SCALE)[:, None, None]  # a missing θh row
    a, b = 0.4, 0.3  # θh = (a - b)/2 = 0.05 rad -> θh index 16, in the hole
    wi = [[np.sin(a), 0, np.cos(a)], [0, 0, 1], [0.6, 0, 0.8], [0.6, 0, -0.8], [0.6, 0, 0.8]]
    wo = [[-np.sin(b), 0, np.cos(b)], [0, 0, 1], [-0.6, 0, 0.8], [0, 0, 1], [0.6, 0, 0.8]]
    wi, wo = jnp.asarray(wi, dtype), jnp.asarray(wo, dtype)
    expect_valid = np.array([False, True, True, False, True])  # hole, ok, ok, below, ok
    for interp in ("nearest", "trilinear"):
        m = MERL(table, interpolation=interp)
        f, valid, i, g = _eval_valid_grad(m, wi, wo)
        f = np.asarray(f)
        assert f.dtype == dtype and f.shape == (5, 3)
        assert np.all(np.isfinite(f)) and np.all(f >= 0)
        assert int(i[0]) == 16
        np.testing.assert_array_equal(np.asarray(valid), expect_valid)
        assert np.all(f[3] == 0)  # below the horizon
        if interp == "nearest":
            assert np.all(f[0] == 0)  # missing cell reads as 0
        else:
            assert np.all(f[0] > 0)  # ...while trilinear uses the valid neighbours
        assert all(np.all(np.isfinite(np.asarray(x))) for x in g)


def test_merl_to_measured(lobe):
    d = merl_to_measured(lobe)
    n_valid = int(np.sum(np.all(np.asarray(lobe.table) >= 0, axis=0)))
    assert len(d) == n_valid and d.channels == ("R", "G", "B")
    assert d.meta["n_missing_cells"] == 90 * 90 * 180 - n_valid
    assert np.all(d.wi[:, 2] > 0) and np.all(d.wo[:, 2] > 0)
    np.testing.assert_allclose(np.linalg.norm(d.wi, axis=1), 1.0, atol=1e-12)
    sub = merl_to_measured(lobe, n=2000, seed=1)
    assert len(sub) == 2000 and len(np.unique(sub.meta["cell"], axis=0)) == 2000
    # Values are the table cells, and looking them up again at the directions agrees.
    np.testing.assert_allclose(np.asarray(_f(lobe, sub.wi, sub.wo)), sub.values, rtol=1e-12)
    i, j, k = sub.meta["cell"].T
    np.testing.assert_array_equal(sub.values, np.asarray(lobe.table)[:, i, j, k].T)


def test_errors_name_the_file(lambert_file, tmp_path):
    good = lambert_file[0].read_bytes()
    trunc = tmp_path / "truncated.binary"
    trunc.write_bytes(good[: FILE_BYTES - 1000])
    with pytest.raises(
        MeasuredDataError, match=r"truncated\.binary.*expected 34992012 bytes.*got 34991012"
    ):
        read_merl(trunc)
    dims = tmp_path / "dims.binary"
    dims.write_bytes(np.asarray([90, 90, 360], "<i4").tobytes() + good[12:])
    with pytest.raises(MeasuredDataError, match=r"dims\.binary.*wrong dimensions \(90, 90, 360\)"):
        read_merl(dims)
    tiny = tmp_path / "tiny.binary"
    tiny.write_bytes(b"\x5a\x00")
    with pytest.raises(ValueError, match=r"tiny\.binary.*too short"):
        read_merl(tiny)
    with pytest.raises(ValueError, match="shape"):
        MERL(jnp.zeros((3, 90, 90, 90)))
    with pytest.raises(ValueError, match="interpolation"):
        MERL(jnp.zeros(MERL_SHAPE), interpolation="cubic")


@pytest.mark.parametrize("n", [0, -5, 2.5, True, "100"])
def test_merl_to_measured_refuses_bad_sample_counts(lobe, n):
    with pytest.raises(ValueError, match=r"n \(merl_samples\) must be a whole number >= 1"):
        merl_to_measured(lobe, n=n)
