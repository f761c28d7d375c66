"""The peer baseline: a per-pixel SVBRDF fit by Adam through a differentiable renderer.

This is what researchers typically run on a phone-flash capture instead of jaxrefl: the
per-pixel mode of svbrdf-diff-renderer (Y. Guo, github.com/tflsguoyu/svbrdf-diff-renderer,
``optim_perpixel``), the renderer and baseline of MaterialGAN (Guo, Smith, Hašan, Sunkavalli
and Zhao, "MaterialGAN: Reflectance Capture using a Generative SVBRDF Model", ACM TOG 39(6),
SIGGRAPH Asia 2020). It is written here in JAX with optax as a **benchmark baseline** for
``benchmarks/real_captures.py``; it is not part of the jaxrefl library and uses none of its
fitting code (only the capture's geometry, :meth:`jaxrefl.io.Capture.per_pixel_geometry`).

Image formation (that renderer's, per pixel x, photo k, channel c; point light)::

    L = P_kc * f_r(wi, wo) * max(n.wi, 0) / r^2
    f_r = d (1 - s) / pi + D F G / (4 (n.wo)(n.wi) + eps)
    D = a^2 / (pi ((n.h)^2 a^2 + 1 - (n.h)^2)^2 + eps),            a = rho^2      (GGX)
    F = s + (1 - s) 2^((-5.55473 (wo.h) - 6.98316) (wo.h))                       (Schlick)
    G = G1(n.wo) G1(n.wi),  G1(c) = c / (c (1 - k) + k),  k = a/2 + eps    (Smith-Schlick)

with wi, wo unit vectors from x to the light and the camera (the sample frame: +z the normal
of the plane), h = (wi + wo)/|wi + wo|, r the distance to the light, P the light's power, every
dot product clamped at 0 and eps = 1e-6 (the renderer's; at n.h = 1 it caps D at about
280, reached at a ~ 0.024, and sends D to 0 as rho -> 0, so a collapsing lobe fades instead
of growing a needle; lengths in cm as in the tool's data). F is the
spherical-Gaussian form of Schlick's (1 - wo.h)^5 (Karis 2013), F0 = s the per-pixel RGB
specular; the Lambert term is scaled by (1 - s) as that renderer does (so ``diffuse`` is not
jaxrefl's ``albedo``: albedo = d (1 - s)).

Parametrisation (that tool's): one texture t in [-1, 1] per pixel with 9 channels: diffuse
RGB d = (t + 1)/2, a slope pair (t_x, t_y) giving the normal n = (t_x, t_y, z)/|.| with
z = sqrt(1 - min(t_x^2 + t_y^2, 1 - eps)), roughness rho = (t + 1)/2 (one channel) and
specular RGB s = (t + 1)/2. Adam steps the raw texture; the renderer sees it clamped to
[-1, 1] (so a value pushed past a bound has zero gradient there, as in the tool).

Loss (that tool's): the mean squared difference of the gamma-encoded images
``clip(L, 1e-4, 1)^(1/2.2)`` between rendering and photo, over every pixel, channel and
training photo. The tool sees a photo as 8-bit values, so saturated and dark pixels enter as
ordinary clipped values (a rendering above 1 is clipped too, so it gets no gradient there).
Here observations with status ok, saturated, dark or censored_mixed
(codes 0, 1, 2, 8 of :class:`jaxrefl.io.ObsStatus`) are used as values; non-finite,
negative, masked and below-horizon ones (codes 3 to 7), which have no value, are left out.

Defaults are the tool's per-pixel baseline (``run.py``: ``optim_perpixel(..., lr=0.01,
epochs=1000, tex_init="random")``): Adam with lr 0.01, betas (0.9, 0.999), eps 1e-8, 1000
steps, all pixels in one batch, random start (d ~ N(0.5, 1/8), s ~ N(0.04, 1/32),
rho ~ N(0.2, 1/16), each clipped to [0, 1]; slopes ~ N(0, 1/4) clipped to [-1, 1]).

Speed: the Adam loop is one jit-compiled program: a ``lax.scan`` over the steps, vectorised
over the pixels of a tile of ``TILE`` pixels, and a ``lax.map`` over the tiles (pixels do
not interact, so this is the full-batch fit; tiles keep the arrays in cache). The wi/wo/h
geometry and the Fresnel factor are computed once. A compiled program is kept per (shape,
steps, dtype), so leave-one-photo-out fits compile once (held-out photos are a weight, not
a shape).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

__all__ = ["PeerFit", "fit_peer", "peer_brdf", "peer_render", "texture_to_maps"]

EPS = 1e-6  # the renderer's epsilon (D, G, the specular denominator, the normal's z)
LOSS_FLOOR = 1e-4  # images are clipped to [LOSS_FLOOR, 1] before gamma encoding in the loss
GAMMA = 2.2
#: Status codes used as values in the loss (ok, saturated, dark, censored_mixed).
TRAIN_CODES = (0, 1, 2, 8)


# --------------------------------------------------------------------------- the model
# Vectors and colours are kept component-first (a leading axis of 3, or tuples of arrays):
# XLA vectorises over the long pixel axes then, not over a trailing axis of 3.


def texture_to_maps(tex: dict[str, jax.Array]) -> dict[str, jax.Array]:
    """Maps from the raw texture (clamped to [-1, 1] first, as the tool does).

    tex: ``diffuse`` (3, H, W), ``slope`` (2, H, W), ``roughness`` (H, W), ``specular``
    (3, H, W). Returns ``diffuse``, ``specular`` (3, H, W) in [0, 1], ``roughness`` rho
    (H, W) in [0, 1] and the unit ``normal`` (3, H, W).
    """
    t = {k: jnp.clip(v, -1.0, 1.0) for k, v in tex.items()}
    sx, sy = t["slope"][0], t["slope"][1]
    z = jnp.sqrt(1.0 - jnp.clip(sx * sx + sy * sy, 0.0, 1.0 - EPS))
    inv = 1.0 / jnp.sqrt(sx * sx + sy * sy + z * z)
    return {
        "diffuse": 0.5 * (t["diffuse"] + 1.0),
        "specular": 0.5 * (t["specular"] + 1.0),
        "roughness": 0.5 * (t["roughness"] + 1.0),
        "normal": jnp.stack([sx * inv, sy * inv, z * inv]),
    }


def _dot0(a, b) -> jax.Array:
    """max(a.b, 0) of two 3-vectors given as sequences of components."""
    return jnp.maximum(a[0] * b[0] + a[1] * b[1] + a[2] * b[2], 0.0)


def _unit(a) -> tuple[jax.Array, jax.Array, jax.Array]:
    inv = 1.0 / jnp.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    return a[0] * inv, a[1] * inv, a[2] * inv


def _shade(n, d, s, rho, wi, wo, h, sg) -> list[jax.Array]:
    """f_r(wi, wo) max(n.wi, 0) per colour channel (module docstring).

    n, wi, wo, h: unit 3-vectors as component sequences (pass the same object for wo and h
    as for wi when light and camera coincide: the dot products are then computed once);
    d, s: the 3 colour channels; rho the roughness; sg = 2^((-5.55473 vh - 6.98316) vh)
    with vh = max(wo.h, 0). All broadcast against each other (same rank).
    """
    nl = _dot0(n, wi)
    nv = nl if wo is wi else _dot0(n, wo)
    nh = nl if h is wi else _dot0(n, h)
    alpha = rho * rho
    a2 = alpha * alpha
    nh2 = nh * nh
    den = nh2 * a2 + (1.0 - nh2)
    dist = a2 / (jnp.pi * den * den + EPS)
    k = 0.5 * alpha + EPS
    g = nv / (nv * (1.0 - k) + k) * (nl / (nl * (1.0 - k) + k))
    lobe = dist * g / (4.0 * nv * nl + EPS) * nl
    return [
        d[c] * (1.0 - s[c]) * (nl / jnp.pi) + (s[c] + (1.0 - s[c]) * sg) * lobe for c in range(3)
    ]


def peer_brdf(maps: dict[str, Any], wi: jax.Array, wo: jax.Array) -> jax.Array:
    """f_r (module docstring) at directions wi, wo (..., 3): (..., 3) [1/sr].

    maps: ``diffuse``, ``specular``, ``normal`` (..., 3) and ``roughness`` (...), of the same
    rank as wi and wo (broadcast through unit axes). Below the horizon (n.wi <= 0) f_r is
    returned as 0, which is all the image formation uses there.
    """
    wi, wo = jnp.asarray(wi), jnp.asarray(wo)

    def comps(a):
        a = jnp.asarray(a)
        return [a[..., i] for i in range(3)]

    n, wi3, wo3 = comps(maps["normal"]), comps(wi), comps(wo)
    h = _unit([wi3[i] + wo3[i] for i in range(3)])
    nl = _dot0(n, wi3)
    out = _shade(
        n,
        comps(maps["diffuse"]),
        comps(maps["specular"]),
        jnp.asarray(maps["roughness"]),
        wi3,
        wo3,
        h,
        _schlick_sg(_dot0(wo3, h)),
    )
    safe = jnp.where(nl > 0, nl, 1.0)
    return jnp.stack([jnp.where(nl > 0, f / safe, 0.0) for f in out], axis=-1)


def _schlick_sg(vh):
    """The spherical-Gaussian Schlick factor 2^((-5.55473 vh - 6.98316) vh)."""
    return jnp.exp2((-5.55473 * vh - 6.98316) * vh)


def _prepare(geo: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Component-first geometry (float64): wi, wo, h (3, K, H, W), sg (K, H, W), P/r^2.

    From :meth:`jaxrefl.io.Capture.per_pixel_geometry` (float64), so that the geometry is
    exactly jaxrefl's. h and the Fresnel factor sg (:func:`_schlick_sg` of wo.h) do not
    depend on the maps and are computed once; when light and camera coincide (a flash),
    wo = h = wi and only ``wi`` is kept.
    """
    wi = np.moveaxis(geo["wi"], -1, 0)
    wo = np.moveaxis(geo["wo"], -1, 0)
    h = wi + wo
    h = h / np.linalg.norm(h, axis=0, keepdims=True)
    vh = np.maximum(np.sum(wo * h, axis=0), 0.0)
    out = {
        "wi": wi,
        "sg": np.exp2((-5.55473 * vh - 6.98316) * vh),
        "irradiance": np.moveaxis(geo["irradiance"], -1, 0),
    }
    if not np.array_equal(wi, wo):
        out.update(wo=wo, h=h)
    return out


def peer_render(maps: dict[str, jax.Array], geo: dict[str, jax.Array]) -> jax.Array:
    """Linear radiance (3, K, *pixels), unclipped: P f_r max(n.wi, 0) / r^2.

    maps: component-first ((3, *pixels), roughness (*pixels)), as :func:`texture_to_maps`
    returns; geo: as :func:`_prepare` returns (pixel axes (H, W) or a flat tile).
    """
    m = {k: v[:, None] for k, v in maps.items() if k != "roughness"}
    wi = geo["wi"]
    out = _shade(
        m["normal"],
        m["diffuse"],
        m["specular"],
        maps["roughness"][None],
        wi,
        geo.get("wo", wi),
        geo.get("h", wi),
        geo["sg"],
    )
    return jnp.stack(out) * geo["irradiance"]


@jax.custom_jvp
def _gamma(x: jax.Array) -> jax.Array:
    return x ** (1.0 / GAMMA)


@_gamma.defjvp
def _gamma_jvp(primals, tangents):
    # d(x^(1/g))/dx = y / (g x): reuses y instead of a second power (x >= 1e-4 here).
    (x,), (t,) = primals, tangents
    y = _gamma(x)
    return y, y / (GAMMA * x) * t


def _encode(x: jax.Array) -> jax.Array:
    """The tool's loss domain: clip(x, 1e-4, 1)^(1/2.2)."""
    return _gamma(jnp.clip(x, LOSS_FLOOR, 1.0))


# --------------------------------------------------------------------------- the fit
@dataclass(frozen=True, eq=False)
class PeerFit:
    """A fitted peer SVBRDF and the cost of fitting it.

    Attributes:
        diffuse, specular: (H, W, 3) the tool's diffuse and specular (F0) RGB maps, in [0, 1].
        roughness: (H, W) rho in [0, 1] (GGX alpha = rho^2).
        normal: (H, W, 3) unit normals in the sample frame.
        fit_s: wall seconds of the Adam run (compiled program only).
        compile_s: wall seconds spent compiling it in this call (0 when reused).
        cpu_s: process CPU seconds of the Adam run (all threads; compilation excluded).
        compile_cpu_s: process CPU seconds of the compilation.
        loss: (steps,) the training loss before each Adam step.
        holdout, steps, lr, seed, dtype: the settings used.
    """

    diffuse: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray
    normal: np.ndarray
    fit_s: float
    compile_s: float
    cpu_s: float
    compile_cpu_s: float
    loss: np.ndarray
    holdout: tuple[int, ...]
    steps: int
    lr: float
    seed: int
    dtype: str

    @property
    def maps(self) -> dict[str, np.ndarray]:
        return {
            "diffuse": self.diffuse,
            "specular": self.specular,
            "roughness": self.roughness,
            "normal": self.normal,
        }

    def predict(self, capture) -> np.ndarray:
        """(K, H, W, C) linear radiance of every photo of ``capture`` (unclipped; the tool's
        renderer clamps it to [0, 1] before anyone sees it, which is how
        ``benchmarks/real_captures.py`` scores the peer)."""
        with _precision(self.dtype):
            geo = _prepare(capture.per_pixel_geometry(dtype=np.float64))
            geo = {k: jnp.asarray(v, self.dtype) for k, v in geo.items()}
            maps = {
                "diffuse": np.moveaxis(self.diffuse, -1, 0),
                "specular": np.moveaxis(self.specular, -1, 0),
                "normal": np.moveaxis(self.normal, -1, 0),
                "roughness": self.roughness,
            }
            maps = {k: jnp.asarray(v, self.dtype) for k, v in maps.items()}
            return np.moveaxis(np.asarray(_render_jit(maps, geo)), 0, -1)


_render_jit = jax.jit(peer_render)


def _precision(dtype: str):
    """float64 needs JAX's x64 mode; float32 runs in either."""
    if np.dtype(dtype) == np.float64 and not jax.config.jax_enable_x64:
        return jax.enable_x64(True)
    return contextlib.nullcontext()


def _init_texture(h: int, w: int, seed: int) -> dict[str, np.ndarray]:
    """The tool's random start (module docstring), as textures in [-1, 1]."""
    rng = np.random.default_rng(seed)

    def tex(mean, sd, shape):
        return np.clip(rng.standard_normal(shape) * sd + mean, 0.0, 1.0) * 2.0 - 1.0

    return {
        "slope": np.clip(rng.standard_normal((2, h, w)) / 4.0, -1.0, 1.0),
        "diffuse": tex(0.5, 1 / 8, (3, h, w)),
        "specular": tex(0.04, 1 / 32, (3, h, w)),
        "roughness": tex(0.2, 1 / 16, (h, w)),
    }


def _to_tiles(a: np.ndarray, size: int, fill: float | None = None) -> np.ndarray:
    """(..., H, W) -> (T, ..., size): row-major pixels in tiles, the last one padded.

    Padding repeats the last pixel (finite geometry), or is ``fill`` when given.
    """
    a = np.asarray(a)
    lead, n = a.shape[:-2], a.shape[-2] * a.shape[-1]
    a = a.reshape(*lead, n)
    pad = -n % size
    if pad:
        rep = np.full((*lead, pad), fill, a.dtype) if fill is not None else a[..., -1:]
        a = np.concatenate([a, np.broadcast_to(rep, (*lead, pad))], axis=-1)
    return np.moveaxis(a.reshape(*lead, -1, size), -2, 0)


def _from_tiles(a: np.ndarray, h: int, w: int) -> np.ndarray:
    """Inverse of :func:`_to_tiles`: (T, ..., size) -> (..., H, W)."""
    a = np.moveaxis(np.asarray(a), 0, -2)
    a = a.reshape(*a.shape[:-2], -1)[..., : h * w]
    return a.reshape(*a.shape[:-1], h, w)


def _adam_tiles(tex0, geo, target, weight, total, lr, *, steps: int):
    """``steps`` Adam steps on the weighted mean gamma-domain squared error.

    Arrays come in pixel tiles (leading axis). Pixels do not interact (Adam is per
    parameter and the loss a sum over pixels divided by the global count ``total``), so
    fitting tile after tile is the full-batch fit, with each tile's arrays in cache. Returns
    the final textures and the loss before each step.
    """
    opt = optax.adam(lr, b1=0.9, b2=0.999, eps=1e-8)

    def fit_tile(tile):
        tex, geo_t, target_t, weight_t = tile

        def loss_fn(tex):
            pred = _encode(peer_render(texture_to_maps(tex), geo_t))
            return jnp.sum(weight_t * (pred - target_t) ** 2) / total

        def step(carry, _):
            tex, state = carry
            loss, grad = jax.value_and_grad(loss_fn)(tex)
            upd, state = opt.update(grad, state, tex)
            return (optax.apply_updates(tex, upd), state), loss

        (tex, _), losses = jax.lax.scan(step, (tex, opt.init(tex)), None, length=steps)
        return tex, losses

    tex, losses = jax.lax.map(fit_tile, (tex0, geo, target, weight))
    return tex, jnp.sum(losses, axis=0)


_COMPILED: dict[Any, Any] = {}
#: Pixels per tile. Measured on 2 cores, 256 x 256 x 9 photos: 48-52 ms a step with tiles of
#: 512 to 2048 pixels, 63 ms with 4096, 130 ms in one batch (cache misses); below 512 the
#: loop's per-iteration overhead dominates (110 ms with 128).
TILE = 1024


def fit_peer(
    capture,
    holdout=(),
    steps: int = 1000,
    lr: float = 0.01,
    seed: int = 0,
    dtype: str = "float32",
) -> PeerFit:
    """Fit the peer's per-pixel SVBRDF to ``capture``'s photos by Adam (module docstring).

    Args:
        capture: a :class:`jaxrefl.io.Capture` with point lights.
        holdout: indices of photos left out of the loss (their predictions still come from
            :meth:`PeerFit.predict`).
        steps: Adam steps (the tool's default 1000).
        lr: Adam's learning rate on the [-1, 1] textures (the tool's default 0.01).
        seed: seed of the random start.
        dtype: ``"float32"`` (the tool's) or ``"float64"``.

    Returns:
        A :class:`PeerFit` with the maps and timings (compile apart).
    """
    if capture.light_pos is None:
        raise ValueError("the peer renderer models point lights only")
    k, h, w, c = capture.shape
    if c != 3:
        raise ValueError(f"the peer renderer fits RGB photos, got {c} channels")
    dtype = np.dtype(dtype).name
    held = np.zeros(k, bool)
    held[np.asarray(holdout, int)] = True
    if held.all():
        raise ValueError("every photo is held out: nothing to fit")
    use = np.isin(capture.status, TRAIN_CODES) & ~held[:, None, None, None]
    use = np.moveaxis(use, -1, 0)  # (C, K, H, W) as the renderer's output
    images = np.moveaxis(capture.images, -1, 0)
    size = min(TILE, h * w)
    with _precision(dtype):
        tiles = {
            "geo": {
                n: _to_tiles(v, size)
                for n, v in _prepare(capture.per_pixel_geometry(dtype=np.float64)).items()
            },
            "target": _to_tiles(np.where(use, images, 0.0), size),
            "weight": _to_tiles(use, size, fill=False),
            "tex0": {n: _to_tiles(v, size) for n, v in _init_texture(h, w, seed).items()},
        }
        tiles = jax.tree.map(lambda a: jnp.asarray(a, dtype), tiles)
        target = _encode(tiles["target"])
        total = jnp.sum(tiles["weight"])
        args = (tiles["tex0"], tiles["geo"], target, tiles["weight"], total)
        args = (*args, jnp.asarray(lr, dtype))
        key = (capture.shape, int(steps), dtype, bool(jax.config.jax_enable_x64))
        key = (*key, size, tuple(sorted(tiles["geo"])))
        compile_s = compile_cpu = 0.0
        program = _COMPILED.get(key)
        if program is None:
            t0, c0 = time.perf_counter(), time.process_time()
            run = jax.jit(lambda *a: _adam_tiles(*a, steps=int(steps)))
            program = run.lower(*args).compile()
            compile_s = time.perf_counter() - t0
            compile_cpu = time.process_time() - c0
            _COMPILED[key] = program
        t0, c0 = time.perf_counter(), time.process_time()
        tex, losses = jax.block_until_ready(program(*args))
        fit_s = time.perf_counter() - t0
        cpu_s = time.process_time() - c0
        tex = {n: jnp.asarray(_from_tiles(v, h, w)) for n, v in tex.items()}
        maps = {n: np.asarray(v) for n, v in texture_to_maps(tex).items()}
    for n in ("diffuse", "specular", "normal"):
        maps[n] = np.ascontiguousarray(np.moveaxis(maps[n], 0, -1))
    return PeerFit(
        diffuse=maps["diffuse"],
        specular=maps["specular"],
        roughness=maps["roughness"],
        normal=maps["normal"],
        fit_s=fit_s,
        compile_s=compile_s,
        cpu_s=cpu_s,
        compile_cpu_s=compile_cpu,
        loss=np.asarray(losses),
        holdout=tuple(int(i) for i in np.flatnonzero(held)),
        steps=int(steps),
        lr=float(lr),
        seed=int(seed),
        dtype=dtype,
    )
