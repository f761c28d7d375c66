"""Photometric-stereo methods on synthetic captures with known normals (noise-free: errors
far below 0.5 degrees), robustness to shadows and highlights, uncalibrated PS and the GBR
ambiguity, light calibration with uncertainty, normal integration, statuses."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaxrefl
from jaxrefl import fit, ps
from jaxrefl.fit import Status

LAMBERT = jaxrefl.brdf.get("lambert")


def _pixels(img, mask):
    return np.moveaxis(img[:, mask], 0, 1)


@pytest.fixture(scope="module")
def sphere():
    """A 32 x 32 sphere under 12 lights with per-image, per-channel intensities (12 lights
    in every test of the closed-form methods: one compilation, shared)."""
    _, n, m = ps.sphere_surface(32, 32)
    lights = ps.spiral_lights(12, 60.0)
    e = np.linspace(0.5, 1.5, 12)[:, None] * np.array([[1.0, 0.8, 0.6]])
    albedo = np.array([0.5, 0.7, 0.9])
    img = ps.render(LAMBERT, {"albedo": albedo}, n, m, lights, e)
    return n, m, lights, e, albedo, img


def test_woodham_exact_with_intensities(sphere):
    n, m, lights, e, albedo, img = sphere
    # Lit in every image only: plain least squares assumes no attached shadows.
    lit = np.all(img[..., 0] > 0, axis=0) & m
    r = ps.woodham(_pixels(img, lit), lights, e)
    err = ps.angular_error(np.asarray(r.normals), n[lit])
    assert err.max() < 1e-4
    np.testing.assert_allclose(
        np.asarray(r.albedo) * np.pi, np.broadcast_to(albedo, (lit.sum(), 3)), rtol=1e-6
    )
    assert np.all(np.asarray(r.status) == Status.CONVERGED)
    # Ignoring the intensities biases the normals: they are honoured, not decoration.
    r1 = ps.woodham(_pixels(img, lit), lights)
    assert ps.angular_error(np.asarray(r1.normals), n[lit]).mean() > 1.0


def test_robust_rejects_shadows_and_highlights(sphere):
    n, m, lights, e, _, img = sphere
    obs = _pixels(img, m).copy()
    rng = np.random.default_rng(0)
    # Highlights: two random lit observations per pixel made 3x brighter plus a constant.
    k = rng.integers(0, obs.shape[1], size=(obs.shape[0], 2))
    rows = np.arange(obs.shape[0])[:, None]
    obs[rows, k] = np.where(obs[rows, k] > 0, obs[rows, k] * 3.0 + 0.3, 0.0)
    ls = ps.woodham(obs, lights, e)
    rb = ps.robust(obs, lights, e)
    err_ls = ps.angular_error(np.asarray(ls.normals), n[m])
    err_rb = ps.angular_error(np.asarray(rb.normals), n[m])
    ok = np.asarray(rb.status) == Status.CONVERGED
    assert ok.mean() > 0.95
    assert np.nanmedian(err_ls) > 5.0
    assert np.nanmedian(err_rb[ok]) < 0.5
    assert np.nanpercentile(err_rb[ok], 90) < 0.5
    # Its settings are one Robust, the method object: without reweighting or the trimmed
    # start it is shadow-free least squares, which the highlights pull away.
    plain = ps.robust(obs, lights, e, None, ps.Robust(iters=0, trim=0.0))
    assert np.nanmedian(ps.angular_error(np.asarray(plain.normals), n[m])) > 5.0
    same = ps.Robust().solve(obs, lights, e, None, None)
    np.testing.assert_array_equal(np.asarray(same.normals), np.asarray(rb.normals))


def test_robust_exact_on_clean_data_with_attached_shadows(sphere):
    n, m, lights, e, _, img = sphere
    rb = ps.robust(_pixels(img, m), lights, e)
    ok = np.asarray(rb.status) == Status.CONVERGED
    err = ps.angular_error(np.asarray(rb.normals), n[m])
    assert ok.mean() > 0.95
    assert np.max(err[ok]) < 0.5


def test_too_few_lights_is_masked_not_an_error(sphere):
    _, m, lights, e, _, img = sphere
    obs = _pixels(img, m)[:4]
    w = np.zeros(obs.shape)
    w[:, :2] = 1.0  # two lights only
    w[1] = 1.0
    w[2, :, 0] = np.nan  # non-finite weights are dropped, never propagated
    r = ps.woodham(obs, lights, e, w)
    st = np.asarray(r.status)
    assert st[0] == Status.MASKED and np.all(np.isnan(np.asarray(r.normals)[0]))
    assert st[1] < Status.MASKED
    assert st[2] == Status.MASKED


@pytest.fixture(scope="module")
def glossy(tmp_path_factory):
    """A 20 x 20 glossy sphere (GGX + Lambert) under 12 lights, written in the DiLiGenT
    layout (16-bit PNGs) and read back: one compiled BRDF fit for the method and the
    layout together."""
    _, n, m = ps.sphere_surface(20, 20)
    lights = ps.spiral_lights(12, 55.0)
    e = np.ones((12, 3))
    params = {"albedo": np.array([0.5, 0.6, 0.7]), "specular": np.full(3, 0.3), "alpha": 0.25}
    img = ps.render(ps.default_model(), params, n, m, lights, e)
    root = ps.save_diligent(tmp_path_factory.mktemp("glossy") / "ball", img, lights, e, m, n)
    cap = ps.load_diligent(root)
    obs, ok = cap.pixels()
    obs = obs.astype(np.float64)
    fit = ps.fit_normal_brdf(obs, cap.lights, cap.intensities, ok, obs >= 1.0)
    return n, m, lights, e, img, fit


def test_brdf_fit_recovers_normals_and_lobe(glossy):
    n, m, lights, e, img, fit = glossy
    err = ps.angular_error(np.asarray(fit.ps.normals), n[m])
    assert np.mean(err) < 0.05 and np.max(err) < 0.5
    alpha = np.asarray(fit.params["alpha"])
    np.testing.assert_allclose(np.median(alpha), 0.25, rtol=5e-3)
    expected = np.broadcast_to([0.5, 0.6, 0.7], (m.sum(), 3))
    # 16-bit quantisation of the PNGs limits the agreement to ~1e-3.
    np.testing.assert_allclose(np.asarray(fit.ps.albedo) * np.pi, expected, rtol=5e-3)
    # The Lambertian methods are biased by the highlights on the same data.
    ls = ps.woodham(_pixels(img, m), lights, e)
    assert np.nanmean(ps.angular_error(np.asarray(ls.normals), n[m])) > 2.0


def test_tilt_parametrisation_is_smooth():
    import jax

    n0 = jnp.array([0.3, -0.2, 0.9]) / jnp.linalg.norm(jnp.array([0.3, -0.2, 0.9]))
    f = jax.jit(lambda uv: ps.tilt_normal(uv, n0))
    np.testing.assert_allclose(np.asarray(f(jnp.zeros(2))), np.asarray(n0), atol=1e-12)
    j = np.asarray(jax.jit(jax.jacfwd(f))(jnp.zeros(2)))
    assert np.all(np.isfinite(j)) and np.linalg.matrix_rank(j) == 2


def test_uncalibrated_known_normals_resolve_the_ambiguity():
    _, n, m = ps.sphere_surface(30, 30)
    m = m & (n[..., 2] > 0.75)  # no attached shadows under lights within 35 degrees
    lights = ps.spiral_lights(10, 35.0)
    e = np.linspace(0.6, 1.4, 10)[:, None] * np.ones((1, 3))
    img = ps.render(LAMBERT, {"albedo": np.full(3, 0.6)}, n, m, lights, e)
    mm = img[:, m].mean(-1).T
    calib = np.zeros(mm.shape[0], bool)
    calib[::50] = True
    assert calib.sum() >= 4
    r = ps.uncalibrated(mm, np.ones(mm.shape[0], bool), calib, n[m][calib])
    assert ps.angular_error(r.normals, n[m]).max() < 1e-4
    assert ps.angular_error(r.lights, lights).max() < 1e-4
    ratio = r.intensities / e[:, 0]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-8)  # relative intensities
    assert r.singular_values[3] < 1e-9 * r.singular_values[0]  # rank 3
    with pytest.raises(ValueError, match="need >= 4"):
        ps.resolve_with_known_normals(np.ones((3, 3)), np.ones((3, 3)))


def test_gbr_leaves_images_unchanged_and_maps_surfaces():
    z, n, m = ps.bump_surface(24, 24)
    b = n[m] * 0.4
    lights = ps.spiral_lights(8, 40.0)
    g = ps.gbr_matrix(0.3, -0.2, 1.5)
    b2, l2 = ps.apply_gbr(b, lights, g)
    np.testing.assert_allclose(b @ lights.T, b2 @ l2.T, atol=1e-12)
    # b' is the scaled normal of the surface lambda z + mu x + nu y.
    i, j = np.mgrid[:24, :24]
    x, y = j - 11.5, -(i - 11.5)
    zx = np.gradient(z, axis=1)  # noqa: F841 (the analytic gradient below is used)
    n2 = b2 / np.linalg.norm(b2, axis=1, keepdims=True)
    zx_t = -n[m][:, 0] / n[m][:, 2]
    zy_t = -n[m][:, 1] / n[m][:, 2]
    ref = np.stack([-(1.5 * zx_t + 0.3), -(1.5 * zy_t - 0.2), np.ones_like(zx_t)], axis=1)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    assert ps.angular_error(n2, ref).max() < 1e-6
    assert x.shape == y.shape


def test_integration_returns_the_known_surface():
    z, n, m = ps.bump_surface(48, 64, height=8.0)
    zt = np.where(m, z - z[m].mean(), np.nan)
    for f, tol in ((ps.poisson, 0.02), (ps.frankot_chellappa, 0.05)):
        zr = f(n, m)
        assert np.all(np.isfinite(zr[m])) and np.all(np.isnan(zr[~m]))
        assert np.nanmax(np.abs(zr - zt)) < tol * np.nanmax(np.abs(zt)), f.__name__


def test_lights_from_shading_and_chrome_highlights():
    # Lambertian points of known normal: >= 4 points, with uncertainty.
    _, n, m = ps.sphere_surface(40, 40)
    lights = ps.spiral_lights(6, 50.0)
    e = np.ones((6, 3)) * np.array([1.0, 0.9, 0.8])
    img = ps.render(LAMBERT, {"albedo": np.full(3, 0.5)}, n, m, lights, e)
    cal = ps.lambertian_sphere_lights(img, m, margin=1.0)
    assert cal.error_deg(lights).max() < 0.2  # the fitted circle is off by a fraction of a pixel
    assert np.all(cal.std_deg < 1.0)
    cal_pts = ps.lights_from_shading(img[:, m], n[m])
    assert cal_pts.error_deg(lights).max() < 1e-6
    np.testing.assert_allclose(cal_pts.intensities / cal_pts.intensities[0], e / e[0], rtol=1e-8)
    noisy = img[:, m] + np.random.default_rng(1).normal(0, 0.01, img[:, m].shape)
    cal_noisy = ps.lights_from_shading(noisy, n[m])
    assert np.all(cal_noisy.std_deg > cal_pts.std_deg)
    assert np.all(cal_noisy.error_deg(lights) < 4 * cal_noisy.std_deg + 0.05)
    with pytest.raises(ValueError, match="need >= 4"):
        ps.lights_from_shading(img[:, m][:, :3], n[m][:3])
    # Chrome sphere: a small highlight where each light reflects towards the camera.
    h, w = 81, 81
    i, j = np.mgrid[:h, :w]
    r0 = 35.0
    chrome_mask = np.hypot(i - 40, j - 40) < r0
    imgs = []
    for lk in lights:
        hv = lk + np.array([0.0, 0.0, 1.0])
        hv /= np.linalg.norm(hv)
        row, col = 40 - hv[1] * r0, 40 + hv[0] * r0
        imgs.append(np.exp(-((i - row) ** 2 + (j - col) ** 2) / 2.0) * chrome_mask)
    cc = ps.chrome_sphere_lights(np.array(imgs), chrome_mask, threshold=0.5)
    assert cc.error_deg(lights).max() < 1.0
    assert np.all(cc.std_deg > 0) and np.all(cc.std_deg < 2.0)
    with pytest.raises(ValueError, match="chrome image 0"):
        ps.chrome_sphere_lights(np.zeros((1, h, w)), chrome_mask)


def test_float32_is_finite(sphere):
    _, m, lights, e, _, img = sphere
    obs = jnp.asarray(_pixels(img, m), jnp.float32)
    r = ps.woodham(obs, lights, e)
    assert r.normals.dtype == jnp.float32
    ok = np.asarray(r.status) < Status.MASKED
    assert np.all(np.isfinite(np.asarray(r.normals)[ok]))


# ----------------------------------------------------------------------------- bad input
def _bad_case(kind):
    """(obs, lights, intensities, weight, argument named) of one refused input."""
    k, c = 4, 3
    lights = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]])
    obs, e, w = np.ones((5, k, c)), np.ones((k, c)), np.ones((5, k, c))
    if kind == "below":
        lights[1] = [0.6, 0.0, -0.8]
    elif kind == "nan_light":
        lights[2, 0] = np.nan
    elif kind == "not_unit":
        lights[3] *= 2.0
    elif kind == "light_shape":
        lights = lights[:3]
    elif kind == "negative_e":
        e[1, 2] = -1.0
    elif kind == "nan_e":
        e[0, 0] = np.nan
    elif kind == "e_shape":
        e = np.ones((k, 2))
    elif kind == "weight_shape":
        w = np.ones((5, k, 1))
    elif kind == "negative_w":
        w[0, 0, 0] = -1.0
    elif kind == "obs_shape":
        obs = np.ones((5, k))
    names = {"nan_e": "intensities", "e_shape": "intensities", "negative_e": "intensities"}
    arg = names.get(kind, "weight" if "_w" in kind or "weight" in kind else "lights")
    return obs, lights, e, w, "obs" if kind == "obs_shape" else arg


@pytest.mark.parametrize("method", ["woodham", "robust"])
@pytest.mark.parametrize(
    "kind",
    ["below", "nan_light", "not_unit", "light_shape", "negative_e", "nan_e", "e_shape",
     "weight_shape", "negative_w", "obs_shape"],
)  # fmt: skip
def test_calibrated_methods_refuse_bad_lights_and_shapes(method, kind):
    obs, lights, e, w, arg = _bad_case(kind)
    with pytest.raises(ps.PSInputError, match=rf"^{arg}: ") as err:
        getattr(ps, method)(obs, lights, e, w)
    assert err.value.where == arg


def test_uncalibrated_and_shading_lights_refuse_degenerate_input():
    rng = np.random.default_rng(0)
    flat = np.tile([0.0, 0.0, 1.0], (10, 1))
    with pytest.raises(ps.PSInputError, match=r"^normals: image 0: .*coplanar"):
        ps.lights_from_shading(np.ones((3, 10)), flat)
    with pytest.raises(ps.PSInputError, match=r"^values: holds NaN"):
        ps.lights_from_shading(np.full((3, 10), np.nan), flat)
    m = rng.uniform(0.1, 1.0, (20, 6))
    use, calib = np.ones(20, bool), np.arange(20) < 5
    with pytest.raises(ps.PSInputError, match=r"^calib_normals: .*singular"):
        ps.uncalibrated(m, use, calib, np.tile([0.0, 0.0, 1.0], (5, 1)))
    for cn in (np.full((5, 3), np.nan), np.ones((4, 3))):
        with pytest.raises(ps.PSInputError, match=r"^calib_normals: must be \(5, 3\)"):
            ps.uncalibrated(m, use, calib, cn)
    m[3, 2] = np.nan
    with pytest.raises(ps.PSInputError, match=r"^m: holds NaN"):
        ps.uncalibrated(m, use, calib, rng.normal(size=(5, 3)))


def test_method_objects_name_and_validate_themselves():
    """The PS methods are option objects: named by kind, written as JSON, checked when
    built; solve_capture refuses a bare string with a message naming the objects."""
    assert set(ps.METHODS) == {"ls", "robust", "brdf"}
    assert ps.Robust(trim=0.1).to_json() == {
        "type": "robust",
        "shadow": 0.05,
        "scale_floor": 1e-3,
        "iters": 5,
        "trim": 0.1,
    }
    j = ps.NormalBRDF(model=ps.default_model()).to_json()
    assert j["type"] == "brdf" and j["model"] == "CookTorrance" and j["config"]["type"]
    assert j["space"] is None
    space = fit.ParamSpace(ps.default_model(), channels=3, grey=("specular",))
    j = ps.NormalBRDF(space=space).to_json()
    assert j["space"]["labels"] == list(space.labels) and "specular.R" not in j["space"]["labels"]
    with pytest.raises(ValueError, match="Robust needs a finite shadow"):
        ps.Robust(shadow=-1.0)
    with pytest.raises(ValueError, match="init must be"):
        ps.NormalBRDF(init="random")
    cap = ps.PSCapture(
        images=np.ones((3, 2, 2, 1), np.float32),
        lights=ps.spiral_lights(3),
        intensities=np.ones((3, 1)),
        mask=np.ones((2, 2), bool),
        usable=np.ones((3, 2, 2, 1), bool),
    )
    with pytest.raises(TypeError, match=r"ps\.METHODS\[name\]\(\)"):
        ps.solve_capture(cap, "ls")
