"""Rusinkiewicz half/difference coordinates: inverse, reciprocity, reference, edges."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxrefl.brdf._rusinkiewicz import from_half_diff, to_half_diff


def _upper(rng, n):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _rotate_vector(v, axis, angle):
    """BRDFRead.cpp rotate_vector (Rodrigues), vectorised over rows of v and angle."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    axis = np.broadcast_to(axis, v.shape)
    dot = np.sum(axis * v, axis=1, keepdims=True)
    return v * c + axis * dot * (1 - c) + np.cross(axis, v) * s


def _brdfread_half_diff(wi, wo):
    """Transcription of MERL BRDFRead.cpp std_coords_to_half_diff_coords ("in" = wi)."""
    half = (wi + wo) / 2.0
    half = half / np.linalg.norm(half, axis=1, keepdims=True)
    theta_h = np.arccos(np.clip(half[:, 2], -1, 1))
    phi_h = np.arctan2(half[:, 1], half[:, 0])
    tmp = _rotate_vector(wi, np.array([0.0, 0.0, 1.0]), -phi_h)
    diff = _rotate_vector(tmp, np.array([0.0, 1.0, 0.0]), -theta_h)
    theta_d = np.arccos(np.clip(diff[:, 2], -1, 1))
    phi_d = np.arctan2(diff[:, 1], diff[:, 0])
    return theta_h, phi_h, theta_d, phi_d


def _wrap(a):
    """Angle difference wrapped to (-π, π]."""
    return np.angle(np.exp(1j * np.asarray(a)))


def test_matches_brdfread_reference_and_ranges():
    rng = np.random.default_rng(1)
    wi, wo = _upper(rng, 4000), _upper(rng, 4000)
    ours = [np.asarray(a) for a in to_half_diff(jnp.asarray(wi), jnp.asarray(wo))]
    ref = _brdfread_half_diff(wi, wo)
    np.testing.assert_allclose(ours[0], ref[0], atol=1e-10)
    np.testing.assert_allclose(ours[2], ref[2], atol=1e-10)
    np.testing.assert_allclose(_wrap(ours[1] - ref[1]), 0.0, atol=1e-9)
    np.testing.assert_allclose(_wrap(ours[3] - ref[3]), 0.0, atol=1e-8)
    assert np.all((ours[0] >= 0) & (ours[0] <= np.pi / 2))
    assert np.all((ours[2] >= 0) & (ours[2] <= np.pi / 2))


def test_known_configurations():
    # Mirror pair about the normal: wh = z, θh = 0, θd = θ, φd = φ of wi.
    th, ph = 0.7, 0.4
    wi = jnp.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    wo = jnp.array([-wi[0], -wi[1], wi[2]])
    a = [float(x) for x in to_half_diff(wi, wo)]
    np.testing.assert_allclose(a, [0.0, 0.0, th, ph], atol=1e-14)
    # wi == wo: wh = wi, θd = 0 (φd undefined -> 0).
    a = [float(x) for x in to_half_diff(wi, wi)]
    np.testing.assert_allclose(a, [th, ph, 0.0, 0.0], atol=1e-14)
    # wi = normal, wo at (θ, 0): wh at θ/2 in the xz plane, wd = (-sin θ/2, 0, cos θ/2).
    wo = jnp.array([np.sin(th), 0.0, np.cos(th)])
    a = [float(x) for x in to_half_diff(jnp.array([0.0, 0.0, 1.0]), wo)]
    np.testing.assert_allclose(a, [th / 2, 0.0, th / 2, np.pi], atol=1e-14)


@pytest.mark.parametrize("dtype,tol", [(jnp.float64, 1e-13), (jnp.float32, 2e-6)])
def test_round_trip_and_reciprocity(dtype, tol):
    rng = np.random.default_rng(2)
    wi = _upper(rng, 3000)
    wo = _upper(rng, 3000)
    # Edge rows: θh = 0 (mirror pairs), wi == wo, both at the normal, grazing.
    wo[:50] = wi[:50] * [-1, -1, 1]
    wo[50:100] = wi[50:100]
    wi[100], wo[100] = [0, 0, 1], [0, 0, 1]
    wi[101], wo[101] = [1, 0, 0], [0, 1, 0]
    wi_j, wo_j = jnp.asarray(wi, dtype), jnp.asarray(wo, dtype)
    hd = to_half_diff(wi_j, wo_j)
    assert all(a.dtype == dtype and a.shape == (3000,) for a in hd)
    np.testing.assert_allclose(np.asarray(hd[0][:50]), 0.0, atol=tol)
    back_i, back_o = from_half_diff(*hd)
    assert back_i.dtype == dtype
    np.testing.assert_allclose(np.asarray(back_i), wi, atol=tol)
    np.testing.assert_allclose(np.asarray(back_o), wo, atol=tol)
    # Swapping wi and wo keeps θh, φh, θd and moves φd by π (mirror of wd about wh).
    sw = to_half_diff(wo_j, wi_j)
    for a, b in ((hd[0], sw[0]), (hd[2], sw[2])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=tol)
    generic = np.asarray(hd[0]) > 1e-3  # φh is round-off where wh is the normal
    d_phi_h = _wrap(np.asarray(sw[1], np.float64) - np.asarray(hd[1], np.float64))
    np.testing.assert_allclose(d_phi_h[generic], 0.0, atol=50 * tol)
    has_phi_d = np.asarray(hd[2]) > 1e-3  # φd is round-off where wi == wo
    d_phi_d = _wrap(np.asarray(sw[3], np.float64) - np.asarray(hd[3], np.float64) - np.pi)
    np.testing.assert_allclose(d_phi_d[has_phi_d], 0.0, atol=50 * tol)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_jit_vmap_and_finite_gradients_at_edges(dtype):
    w = np.array([0.3, -0.2, 0.0])
    w[2] = np.sqrt(1 - w @ w)
    edges = [
        (w, w * [-1, -1, 1]),  # θh = 0
        (w, w),  # θd = 0
        ([0, 0, 1], [0, 0, 1]),  # both at the normal
        ([0, 0, 1], w),
        ([1e-6, 0, np.sqrt(1 - 1e-12)], [0, 0, 1]),  # nearly the normal
    ]
    wi = jnp.asarray([e[0] for e in edges], dtype)
    wo = jnp.asarray([e[1] for e in edges], dtype)

    def total(a, b):
        th, ph, td, pd = to_half_diff(a, b)
        wi2, wo2 = from_half_diff(th, ph, td, pd)
        return jnp.sum(th + ph + td + pd) + jnp.sum(wi2 + wo2)

    gi, go = jax.jit(jax.grad(total, argnums=(0, 1)))(wi, wo)
    assert np.all(np.isfinite(np.asarray(gi))) and np.all(np.isfinite(np.asarray(go)))
    vm = jax.vmap(to_half_diff)(wi, wo)
    full = to_half_diff(wi, wo)
    for a, b in zip(vm, full, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6)


def test_gradients_match_finite_differences():
    wi = jnp.array([0.3, -0.2, 0.9])
    wo = jnp.array([-0.5, 0.4, 0.6])
    check_grads(lambda a, b: jnp.stack(to_half_diff(a, b)), (wi, wo), order=1, modes=["rev"])
    args = tuple(jnp.array(x) for x in (0.3, 0.5, 0.6, -1.0))
    check_grads(lambda *a: jnp.concatenate(from_half_diff(*a)), args, order=1, modes=["rev"])
