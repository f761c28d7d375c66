"""Image formation: render() against closed forms, shapes, shadows, gradients and edges."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxrefl
from jaxrefl import scene
from jaxrefl.brdf import BRDF, Param

LAMBERT = jaxrefl.brdf.get("lambert")
UP = scene.OrthographicCamera()


class ToySpecular(BRDF):
    """Lambert + a Beckmann-like lobe, only for these tests (other models are written
    elsewhere): f = albedo/pi + exp(-tan^2 th_h/alpha^2)/(pi alpha^2 cos^4 th_h 4 cos_i cos_o)."""

    @property
    def params(self):
        return (
            Param("albedo", "color", 0.5, 0.0, 1.0, "1", "diffuse albedo"),
            Param("alpha", "scalar", 0.3, 1e-4, 1.0, "1", "lobe width"),
        )

    def _eval(self, p, wi, wo):
        h = wi + wo
        h = h / jnp.linalg.norm(h, axis=-1, keepdims=True)
        c2 = h[..., 2] ** 2
        a2 = p["alpha"] ** 2
        d = jnp.exp(-(h[..., 0] ** 2 + h[..., 1] ** 2) / (c2 * a2)) / (jnp.pi * a2 * c2 * c2)
        spec = d / (4.0 * wi[..., 2] * wo[..., 2])
        return p["albedo"] / jnp.pi + spec[..., None]


class Probe(BRDF):
    """f = albedo (2 + wi_x): reveals the local x coordinate (the tangent) of wi."""

    @property
    def params(self):
        return (Param("albedo", "color", 0.5, 0.0, 1.0, "1", "scale"),)

    @property
    def reciprocal(self):
        return False

    def _eval(self, p, wi, wo):
        return p["albedo"] * (2.0 + wi[..., 0:1]) + 0.0 * wo[..., 0:1]


def test_lambert_under_directional_light_is_exact():
    d = np.array([0.3, -0.4, 0.866])
    e = np.array([1.0, 2.0, 3.0])
    albedo = jnp.array([[[0.2, 0.5, 0.9]]]) * jnp.linspace(0.5, 1.0, 12).reshape(3, 4, 1)
    img = scene.render_planar_sample(
        LAMBERT, {"albedo": albedo}, scene.DirectionalLight(d, e), UP, image_size=(3, 4), side=5.0
    )
    assert img.shape == (1, 3, 4, 3)
    cos = d[2] / np.linalg.norm(d)
    np.testing.assert_allclose(img[0], albedo / np.pi * e.reshape(1, 1, 3) * cos, rtol=1e-14)


def test_near_point_light_pinhole_camera_cos4_and_response_order():
    lp, cp, inten = np.array([2.0, 1.0, 6.0]), np.array([-1.0, 0.5, 10.0]), 50.0
    cam = scene.PinholeCamera(cp)
    pts = scene.planar_points(5, 4, 6.0)
    kw = {"points": pts}
    lin = scene.render(LAMBERT, {"albedo": 0.4}, scene.PointLight(lp, inten), cam, **kw)
    x = np.asarray(pts)
    r2 = np.sum((lp - x) ** 2, -1)
    cos_i = (lp[2] - x[..., 2]) / np.sqrt(r2)
    ray = x - cp
    axis = -cp / np.linalg.norm(cp)
    cos_c = (ray @ axis) / np.linalg.norm(ray, axis=-1)
    expect = 0.4 / np.pi * inten / r2 * cos_i * cos_c**4
    np.testing.assert_allclose(lin[0, ..., 0], expect, rtol=1e-13)
    assert lin[0, 0, 0, 0] != lin[0, 4, 3, 0]  # a near light varies across the sample
    resp = scene.GammaResponse(exposure=5.0)
    enc = scene.render(
        LAMBERT, {"albedo": 0.4}, scene.PointLight(lp, inten), cam, response=resp, **kw
    )
    np.testing.assert_allclose(enc, resp.apply(lin), rtol=1e-14)  # response last
    no4 = scene.render(LAMBERT, {"albedo": 0.4}, scene.PointLight(lp, inten), cam, cos4=False, **kw)
    np.testing.assert_allclose(no4[0, ..., 0], expect / cos_c**4, rtol=1e-13)


def test_shapes_stacking_chunking_and_camera_sequences():
    pts = scene.planar_points(4, 5, 3.0)
    p = {"albedo": jnp.array([0.3, 0.5, 0.7])}
    lights = [scene.PointLight([x, 0.0, 8.0], 10.0) for x in (-1.0, 0.0, 2.0)]
    cams = [scene.PinholeCamera([x, 1.0, 9.0]) for x in (0.5, 0.0, -1.0)]
    stacked = scene.render(LAMBERT, p, lights, cams, points=pts)  # one layout: lax.map path
    assert stacked.shape == (3, 4, 5, 3)
    singles = [
        scene.render(LAMBERT, p, lt, c, points=pts)[0] for lt, c in zip(lights, cams, strict=True)
    ]
    np.testing.assert_allclose(stacked, np.stack(singles), rtol=1e-14)
    chunked = scene.render(LAMBERT, p, lights, cams, points=pts, chunk_samples=7)
    np.testing.assert_allclose(chunked, stacked, rtol=1e-14)
    # Mixed kinds (loop path); a grey environment beside RGB lights broadcasts to C = 3.
    env = scene.EnvironmentMap(jnp.ones((4, 8)))
    area = scene.AreaLight([0.0, 0.0, 5.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [1.0, 2.0, 3.0], n=2)
    mixed = scene.render(LAMBERT, {"albedo": 0.5}, [env, area, lights[0]], cams[0], points=pts)
    assert mixed.shape == (3, 4, 5, 3)
    np.testing.assert_allclose(
        mixed[2],
        scene.render(LAMBERT, {"albedo": 0.5}, lights[0], cams[0], points=pts)[0, ..., 0:1].repeat(
            3, -1
        ),
    )
    with pytest.raises(ValueError, match="cameras"):
        scene.render(LAMBERT, p, lights, cams[:2], points=pts)
    with pytest.raises(KeyError, match="albedo"):
        scene.render(LAMBERT, {}, lights, cams[0], points=pts)


def test_shadow_mask_multiplies_each_light():
    pts = scene.planar_points(3, 3, 2.0)
    lights = [scene.PointLight([0.0, 0.0, 4.0], 1.0), scene.PointLight([1.0, 0.0, 4.0], 2.0)]
    full = scene.render(LAMBERT, {"albedo": 0.5}, lights, UP, points=pts)
    mask = np.ones((2, 3, 3))
    mask[0, 1, :] = 0.0
    mask[1, 2, 2] = 0.25
    shaded = scene.render(LAMBERT, {"albedo": 0.5}, lights, UP, points=pts, shadow=mask)
    np.testing.assert_array_equal(shaded[0, 1], 0.0)
    np.testing.assert_allclose(shaded, full * mask[..., None], rtol=1e-15)
    # Per-sample visibility of an area light: blocking node 0 removes exactly its share.
    area = scene.AreaLight([0.5, 0.0, 2.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], 1.0, n=2)
    vis = np.ones((1, 3, 3, 4))
    vis[..., 0] = 0.0
    part = scene.render(LAMBERT, {"albedo": 0.5}, area, UP, points=pts, shadow=vis)
    wi, e = area.incident(pts)
    manual = 0.5 / np.pi * np.sum((e[..., 0] * np.maximum(wi[..., 2], 0))[..., 1:], -1)
    np.testing.assert_allclose(part[0, ..., 0], manual, rtol=1e-14)
    with pytest.raises(ValueError, match="shadow"):
        scene.render(LAMBERT, {"albedo": 0.5}, lights, UP, points=pts, shadow=np.ones((3, 3)))


def test_gradients_match_finite_differences_float64():
    pts = scene.planar_points(3, 3, 4.0)
    lights = [scene.PointLight([1.0, 0.5, 3.0], 20.0), scene.PointLight([-1.0, 0.0, 3.0], 20.0)]
    cams = [scene.PinholeCamera([0.8, 0.4, 4.0]), scene.PinholeCamera([-0.5, 0.0, 4.0])]
    model = ToySpecular()
    resp = scene.SRGBResponse(exposure=0.05, clip=False)
    w = jnp.asarray(np.random.default_rng(0).uniform(size=(2, 3, 3, 3)))

    def loss(albedo, alpha):
        img = scene.render(
            model, {"albedo": albedo, "alpha": alpha}, lights, cams, points=pts, response=resp
        )
        return jnp.sum(w * img)

    albedo = jnp.full((3, 3, 3), 0.4) + 0.1 * jnp.arange(3.0).reshape(1, 1, 3)
    alpha = jnp.linspace(0.2, 0.6, 9).reshape(3, 3)
    check_grads(loss, (albedo, alpha), order=1, modes=("rev",), eps=1e-6, atol=1e-7, rtol=1e-6)
    ga, gl = jax.grad(loss, argnums=(0, 1))(albedo, alpha)
    assert ga.shape == albedo.shape and gl.shape == alpha.shape
    assert np.all(np.abs(np.asarray(gl)) > 0)  # every pixel's highlight depends on alpha


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_no_nan_below_the_horizon(dtype):
    # Pixel normals facing away from the light, a light exactly at 90 degrees, a camera
    # below one pixel's horizon: those pixels are 0, and every gradient stays finite.
    nrm = jnp.array([[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.6, -0.8]]], dtype)
    pts = jnp.zeros((1, 4, 3), dtype)
    lights = [
        scene.DirectionalLight([0.0, 0.0, 1.0], 1.0),
        scene.DirectionalLight([1.0, 0.0, 0.0], 1.0),
    ]
    model = ToySpecular()

    def img(albedo, alpha, normals, lpos):
        ls = [*lights, scene.PointLight(lpos, 5.0)]
        p = {"albedo": albedo, "alpha": alpha}
        return scene.render(
            model, p, ls, UP, points=pts, normals=normals, response=scene.GammaResponse()
        )

    args = (
        jnp.array([0.5], dtype),
        jnp.asarray(0.2, dtype),
        nrm,
        jnp.array([0.0, 0.0, -2.0], dtype),
    )
    out = img(*args)
    assert out.dtype == dtype
    assert np.all(np.isfinite(out))
    assert float(out[0, 0, 0, 0]) > 0
    np.testing.assert_array_equal(out[0, 0, 1:], 0.0)  # normals away from the light / camera
    np.testing.assert_array_equal(out[1, 0, 0], 0.0)  # light at exactly 90 degrees
    np.testing.assert_array_equal(out[2], 0.0)  # point light below the plane
    grads = jax.grad(lambda *a: jnp.sum(img(*a)), argnums=(0, 1, 2, 3))(*args)
    for g in grads:
        assert np.all(np.isfinite(g))


def test_tangents_set_the_local_x_axis():
    light = scene.DirectionalLight([0.6, 0.0, 0.8], 1.0)
    pts = jnp.zeros((1, 1, 3))
    default = scene.render(Probe(), {"albedo": 1.0}, light, UP, points=pts, cos4=False)
    along_y = scene.render(
        Probe(), {"albedo": 1.0}, light, UP, points=pts, tangents=[0.0, 1.0, 0.0], cos4=False
    )
    np.testing.assert_allclose(default[0, 0, 0, 0], 2.6 * 0.8, rtol=1e-14)  # t = +x: wi_x = 0.6
    np.testing.assert_allclose(along_y[0, 0, 0, 0], 2.0 * 0.8, rtol=1e-14)  # t = +y: wi_x = 0


@pytest.mark.slow
def test_megapixel_nine_lights_fits_in_memory_float32():
    # The MaterialGAN capture size: 1024 x 1024, 9 flash positions with moving cameras.
    ang = np.linspace(0.0, 2 * np.pi, 9, endpoint=False)
    lights = [scene.PointLight([2 * np.cos(a), 2 * np.sin(a), 20.0], [300.0] * 3) for a in ang]
    cams = [scene.PinholeCamera([2 * np.cos(a), 2 * np.sin(a), 24.0]) for a in ang]
    albedo = jnp.full((1024, 1024, 3), 0.5, jnp.float32)
    f = eqx.filter_jit(
        lambda a: scene.render_planar_sample(
            LAMBERT, {"albedo": a}, lights, cams, image_size=1024, side=11.0, dtype=jnp.float32,
            response=scene.GammaResponse(),
        )
    )  # fmt: skip
    out = f(albedo)
    assert out.shape == (9, 1024, 1024, 3) and out.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(out[:, ::64, ::64])))
    assert float(out.min()) > 0.0 and float(out.max()) <= 1.0


def test_parameter_shapes_are_checked():
    pts = scene.planar_points(3, 4, 1.0)
    with pytest.raises(ValueError, match="trailing channel axis"):  # (H, W) albedo, no C
        scene.render(
            LAMBERT,
            {"albedo": jnp.ones((3, 4))},
            scene.PointLight([0, 0, 1.0], 1.0),
            UP,
            points=pts,
        )
