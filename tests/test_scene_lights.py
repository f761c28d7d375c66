"""Lights and geometry of jaxrefl.scene: exact irradiance laws and quadrature accuracy."""

import itertools
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

import jaxrefl
from jaxrefl import scene

LAMBERT = jaxrefl.brdf.get("lambert")
UP = scene.OrthographicCamera()
# One compiled call per light layout instead of eager op-by-op dispatch (test speed only).
_incident = eqx.filter_jit(lambda light, x: light.incident(x))


# ---------------------------------------------------------------------------- geometry
def test_orthonormal_basis_is_right_handed_everywhere():
    # Random normals plus the cases the branchless form of Duff et al. 2017 exists for:
    # the poles, the equator (n_z = +-0) and normals just beside -z.
    rng = np.random.default_rng(1)
    n = rng.normal(size=(200, 3))
    extra = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 1, -0.0], [1e-7, 2e-7, -1], [1e-4, 0, -1]]
    n = np.concatenate([n, np.asarray(extra, float)])
    n = jnp.asarray(n / np.linalg.norm(n, axis=1, keepdims=True))
    t, b = scene.orthonormal_basis(n)
    m = jnp.stack([t, b, n], axis=-2)  # rows t, b, n
    np.testing.assert_allclose(
        m @ jnp.swapaxes(m, -1, -2), np.broadcast_to(np.eye(3), m.shape), atol=2e-15
    )
    np.testing.assert_allclose(jnp.cross(t, b), n, atol=2e-15)
    # The planar-sample normal gives the world axes.
    t0, b0 = scene.orthonormal_basis(jnp.array([0.0, 0.0, 1.0]))
    np.testing.assert_array_equal(t0, [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(b0, [0.0, 1.0, 0.0])
    g = jax.jacfwd(lambda v: jnp.concatenate(scene.orthonormal_basis(v)))(
        jnp.array([0.0, 0.0, -1.0])
    )
    assert np.all(np.isfinite(g))


@pytest.mark.parametrize("z", [0.0, -0.0], ids=["+0", "-0"])
def test_orthonormal_basis_takes_the_sign_of_a_signed_zero(z):
    """n_z = -0.0 takes s = -1 and +0.0 takes s = +1 (copysign, Duff et al. 2017 listing 3):
    both frames are right-handed and orthonormal, with finite derivatives. This is the one
    frame of the package: the posterior's light likelihood uses it too."""
    nx, ny = 0.6, 0.8
    n = jnp.array([nx, ny, z])
    t, b = scene.orthonormal_basis(n)
    s = float(np.copysign(1.0, z))
    a = -1.0 / s  # -1/(s + n_z)
    np.testing.assert_allclose(t, [1 + s * nx * nx * a, s * nx * ny * a, -s * nx], atol=1e-15)
    np.testing.assert_allclose(b, [nx * ny * a, s + ny * ny * a, -ny], atol=1e-15)
    m = jnp.stack([t, b, n])
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=2e-15)
    np.testing.assert_allclose(jnp.cross(t, b), n, atol=2e-15)
    g = jax.jacfwd(lambda v: jnp.concatenate(scene.orthonormal_basis(v)))(n)
    assert np.all(np.isfinite(g))
    assert not hasattr(jaxrefl.posterior, "onb") and not hasattr(jaxrefl.posterior, "to_local")


def test_local_world_round_trip_and_tangent_projection():
    n = jnp.array([[0.0, 0.6, 0.8], [0.0, 0.0, 1.0]])
    tangent = jnp.array([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # second: parallel to n
    nn, t, b = scene.shading_frame(n, tangent)
    np.testing.assert_allclose(jnp.sum(t * nn, -1), 0.0, atol=1e-15)
    np.testing.assert_allclose(jnp.linalg.norm(t, axis=-1), 1.0, rtol=1e-15)
    # Gram-Schmidt keeps the tangent in the plane spanned by (tangent, n).
    tp = tangent[0] - jnp.dot(tangent[0], n[0]) * n[0]
    np.testing.assert_allclose(t[0], tp / jnp.linalg.norm(tp), rtol=1e-14)
    # A tangent along the normal falls back to the Duff basis.
    np.testing.assert_allclose(t[1], [1.0, 0.0, 0.0], atol=1e-15)
    v = jnp.array([[0.3, -0.2, 0.9], [0.1, 0.5, -0.4]])
    loc = scene.to_local(v, nn, t, b)
    np.testing.assert_allclose(loc[:, 2], jnp.sum(v * nn, -1), rtol=1e-14)
    np.testing.assert_allclose(scene.to_world(loc, nn, t, b), v, atol=1e-15)


def test_planar_points_follow_the_flash_capture_convention():
    # ../shared/data/README.md: x = ((j + 0.5)/W - 0.5) S, y = -((i + 0.5)/H - 0.5) S, z = 0.
    p = scene.planar_points(4, 8, 16.0)
    assert p.shape == (4, 8, 3)
    np.testing.assert_allclose(p[0, 0], [-7.0, 6.0, 0.0])  # top-left pixel
    np.testing.assert_allclose(p[3, 7], [7.0, -6.0, 0.0])  # bottom-right
    np.testing.assert_allclose(p[2, 5], [(5.5 / 8 - 0.5) * 16, -(2.5 / 4 - 0.5) * 16, 0.0])


# ---------------------------------------------------------------------------- point lights
def test_point_light_inverse_square_and_per_pixel_directions():
    light = scene.PointLight([1.0, -2.0, 5.0], [40.0, 20.0, 10.0])
    x = scene.planar_points(5, 6, 8.0)
    wi, e = _incident(light, x)
    assert wi.shape == (5, 6, 1, 3) and e.shape == (5, 6, 1, 3)
    d = np.asarray([1.0, -2.0, 5.0]) - np.asarray(x)
    r2 = np.sum(d * d, axis=-1)
    np.testing.assert_allclose(wi[..., 0, :], d / np.sqrt(r2)[..., None], rtol=1e-14)
    np.testing.assert_allclose(
        e[..., 0, :], np.asarray([40.0, 20.0, 10.0]) / r2[..., None], rtol=1e-14
    )

    # Radiance of a Lambert plane at normal incidence: doubling the distance quarters it.
    def at_height(h):
        lt = scene.PointLight([0.0, 0.0, h], 1.0)
        pts = jnp.zeros((1, 1, 3))
        return scene.render(LAMBERT, {"albedo": 0.5}, lt, UP, points=pts, cos4=False)[0, 0, 0, 0]

    np.testing.assert_allclose(at_height(3.0) / at_height(6.0), 4.0, rtol=1e-14)
    np.testing.assert_allclose(at_height(3.0), 0.5 / np.pi / 9.0, rtol=1e-14)


def test_point_light_at_the_surface_point_gives_zero_not_nan():
    light = scene.PointLight([0.0, 0.0, 0.0], 1.0)
    g = jax.grad(lambda p: light.incident(p)[1].sum())(jnp.zeros(3))
    assert float(light.incident(jnp.zeros(3))[1].sum()) == 0.0
    assert np.all(np.isfinite(g))


# ---------------------------------------------------------------------------- area lights
def _form_factor_corner(a, b):
    """Differential area to a parallel rectangle a x b (in units of the height) with one corner
    straight above it (Howell, "A catalog of radiation heat transfer configuration factors",
    B-3)."""
    ra, rb = np.sqrt(1 + a * a), np.sqrt(1 + b * b)
    return (a / ra * np.arctan(b / ra) + b / rb * np.arctan(a / rb)) / (2 * np.pi)


@pytest.mark.parametrize("w", [0.5, 2.0])
def test_area_light_matches_the_exact_form_factor(w):
    # Square of side 2w at height 1 facing down (u x v = y x x = -z); irradiance below its
    # centre is pi L F with F four times the corner form factor.
    lum = 3.0
    exact = np.pi * lum * 4 * _form_factor_corner(w, w)
    errors = []
    for n in (2, 4, 8, 16):
        light = scene.AreaLight([0, 0, 1.0], [0, 2 * w, 0], [2 * w, 0, 0], lum, n=n)
        wi, e = _incident(light, jnp.zeros(3))
        errors.append(abs(float(jnp.sum(e[:, 0] * wi[:, 2])) / exact - 1))
    # Measured at n = 16: 1e-12 (w = 0.5), 3e-6 (w = 2: the square subtends 126 degrees).
    assert errors[-1] < 1e-5
    assert all(b < a for a, b in itertools.pairwise(errors))
    # The back of the emitter is dark.
    flipped = scene.AreaLight([0, 0, 1.0], [2 * w, 0, 0], [0, 2 * w, 0], lum)
    assert float(jnp.sum(_incident(flipped, jnp.zeros(3))[1])) == 0.0


def test_area_light_converges_to_a_point_light():
    # Fixed L * A: far field I(theta_l) = L A cos(theta_l); error O((size/r)^2).
    c = np.array([0.5, -0.3, 3.0])
    nl = np.array([0.3, 0.1, -1.0])
    nl /= np.linalg.norm(nl)
    u0 = np.cross(nl, [1.0, 0.0, 0.0])
    u0 /= np.linalg.norm(u0)
    v0 = np.cross(nl, u0)
    pts = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0], [-1.0, -1.0, 0.2], [2.0, 0.0, 0.0]])
    la = 10.0
    d = c - np.asarray(pts)
    r = np.linalg.norm(d, axis=1)
    cos_l = -(d / r[:, None]) @ nl
    _, e_p = _incident(scene.PointLight(c, 1.0), pts)
    ref = la * cos_l * e_p[:, 0, 0]
    errs = []
    for s in (2.0, 1.0, 0.5, 0.25, 0.125):
        light = scene.AreaLight(c, u0 * s, v0 * s / 2, la / (s * s / 2), n=4)
        np.testing.assert_allclose(light.normal, nl, rtol=1e-14)
        _, e = _incident(light, pts)
        errs.append(np.abs(np.sum(e[..., 0], -1) / ref - 1).max())
    ratios = np.asarray(errs[:-1]) / np.asarray(errs[1:])
    assert np.all((ratios > 3.5) & (ratios < 4.5)), (errs, ratios)  # second order
    assert errs[-1] < 5e-4  # measured 2.2e-4 at size/r = 0.04


# ---------------------------------------------------------------------------- environment
def test_environment_orientation_and_solid_angles():
    h, w = 8, 16
    env = scene.EnvironmentMap(jnp.ones((h, w, 2)))
    d, domega, lum = env.texels()
    assert d.shape == (h, w, 3) and domega.shape == (h, w) and lum.shape == (h, w, 2)
    th, ph = np.pi / (2 * h), np.pi / w  # centre of row 0, column 0
    np.testing.assert_allclose(
        d[0, 0], [np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)]
    )
    np.testing.assert_allclose(d[h - 1, w // 4, 2], -np.cos(th), rtol=1e-14)  # last row: nadir
    np.testing.assert_allclose(jnp.sum(domega), 4 * np.pi, rtol=1e-14)
    # A light only in the texel straight above +x (theta ~ pi/2, phi ~ 0) lights +x normals.
    img = np.zeros((h, w, 1))
    img[h // 2 - 1, 0] = 1.0
    wi, e = _incident(scene.EnvironmentMap(img), jnp.zeros((3,)))
    k = int(np.argmax(np.asarray(e[:, 0])))
    assert wi[k, 0] > 0.9 and wi[k, 1] > 0 and wi[k, 2] > 0


def test_subsampling_keeps_power_and_rotation_moves_the_sky():
    rng = np.random.default_rng(2)
    img = rng.uniform(size=(16, 32, 3))
    full, half = scene.EnvironmentMap(img), scene.EnvironmentMap(img, subsample=4)
    _, e_full = _incident(full, jnp.zeros(3))
    _, e_half = _incident(half, jnp.zeros(3))
    assert e_half.shape == (32, 3)
    np.testing.assert_allclose(e_half.sum(0), e_full.sum(0), rtol=1e-13)
    rot = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    wi_r, _ = _incident(scene.EnvironmentMap(img, rotation=rot), jnp.zeros(3))
    wi_0, _ = _incident(full, jnp.zeros(3))
    np.testing.assert_allclose(wi_r, wi_0 @ rot.T, atol=1e-15)
    with pytest.raises(ValueError, match="divide"):
        scene.EnvironmentMap(img, subsample=3)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_constant_environment_on_lambert_reflects_albedo_times_radiance(dtype):
    # Irradiance of a constant sky L is pi L on any plane, so a Lambert surface of albedo a
    # reflects a L whatever its normal (quadrature error O(1/H^2): measured 1.2e-3 at H = 32).
    lum, albedo = 2.0, jnp.array([0.2, 0.5, 0.9])
    env = scene.EnvironmentMap(jnp.full((32, 64, 1), lum))
    rng = np.random.default_rng(3)
    nrm = rng.normal(size=(3, 4, 3))
    nrm[0, 0] = [0.0, 0.0, 1.0]
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    pts = jnp.zeros((3, 4, 3), dtype)
    cam = scene.OrthographicCamera([0.0, 0.0, 1.0])
    img = scene.render(LAMBERT, {"albedo": albedo}, env, cam, points=pts, normals=nrm, cos4=False)
    assert img.dtype == dtype
    # The camera at +z sees only normals facing it; the others are 0 exactly (wo below horizon).
    seen = np.asarray(nrm[..., 2] > 0)
    np.testing.assert_allclose(
        img[0][seen], np.broadcast_to(albedo * lum, (seen.sum(), 3)), rtol=2e-3
    )
    assert np.all(np.asarray(img[0])[~seen] == 0.0)


def test_planar_convention_places_real_flash_highlights(shared_data):
    # MaterialGAN bath tile (Guo et al. 2020): 9 phone photos, flash beside the lens. The
    # brightest (blurred) region of each photo lies near the mirror point of the flash on the
    # plane; its pixel under planar_points must track the measured one along both image axes
    # (a flipped row or column convention gives a negative correlation). Measured: r = 0.95
    # (rows) and 0.99 (columns); offsets of ~100 px come from the texture and the blur.
    root = shared_data / "svbrdf_flash" / "bath_tile"
    meta = json.loads((root / "parameters.json").read_text())
    pts = np.asarray(scene.planar_points(256, 256, meta["image_size"]))[..., :2]
    found, predicted = [], []
    for k, (c, lt) in enumerate(zip(meta["camera_pos"], meta["light_pos"], strict=True)):
        img = np.asarray(Image.open(root / "images" / "reference" / "1024" / f"{k:02d}.png"))
        grey = ndimage.gaussian_filter(img[::4, ::4, :3].astype(float).mean(-1), 6)
        found.append(np.unravel_index(np.argmax(grey), grey.shape))
        c, lt = np.asarray(c), np.asarray(lt)
        mirror = (c[2] * lt[:2] + lt[2] * c[:2]) / (c[2] + lt[2])
        predicted.append(np.unravel_index(np.argmin(np.sum((pts - mirror) ** 2, -1)), (256, 256)))
    found, predicted = np.asarray(found), np.asarray(predicted)
    for axis in (0, 1):
        assert np.corrcoef(found[:, axis], predicted[:, axis])[0, 1] > 0.85
