"""Where to take the next photo: candidate camera-and-flash positions ranked by information.

Criterion (Bayesian D-optimal design, Chaloner & Verdinelli 1995, section 2.2; the
capture-wide form of :func:`jaxrefl.measured.rank_candidates`): the expected information
gain of a new photo c about the parameters of the fit,

    gain_c = 1/2 ln det(A + F_c) - 1/2 ln det(A) = 1/2 ln det(I + Sigma F_c)     [nats]

the mutual information between the photo and the parameters under the linearised model:
by how much (a factor exp(-gain_c)) the volume of the posterior shrinks. (The measured
planner's ``gain`` is the log-volume ratio of the precision, twice this.)

* A, the current posterior precision, is the fit's Laplace one (:func:`jaxrefl.fit.laplace`):
  per pixel J^T J / s^2 of the fit's residual (its noise model, robust loss, censoring and
  priors: ``pooled``'s F0 prior, ``ggx_normal``'s slope prior) at the fit's theta on its
  training photos, s^2 the Laplace noise scale (estimated per pixel, or the known one), plus
  a weak prior I / ``prior_width``^2 in theta units (as the measured planner; it keeps a
  pixel whose lobe no photo saw, a singular J^T J, finite).
* F_c, the Fisher information of the new photo, linearised at the fit's theta: per pixel
  and channel y = f_r(theta; wi, wo) E cos_i (the capture model's ``eval`` and the
  capture's point light, :meth:`jaxrefl.io.Capture.per_pixel_geometry`), noise variance
  v = s^2 std(y)^2 of the fit's noise model at the predicted value, and
  F = sum_c lambda_c j_c j_c^T / v_c with j_c = dy_c / dtheta (``jax.jacfwd``). lambda_c in
  (0, 1] is the censoring factor (:func:`censoring_factor`): an observation that may
  saturate (at the capture's ``saturation_level``) or clip dark (``dark_level``) is a
  censored (Tobit) observation, whose information is that of the uncensored one times
  lambda; a highlight predicted far above the saturation level informs almost nothing.
  The robust loss is not applied to the new photo (its information is the inliers').
* Pixels are independent given the parameters they share: ``pooled``'s one GGX width is
  one parameter of the whole capture, counted once. The joint precision is then
  block-arrow (pixel blocks A_i, their coupling b_i to the shared width, its own entry) and

      ln det = sum_i ln det A_i + ln det(S),   S = tau^-2 + sum_i (c_i - b_i^T A_i^-1 b_i)

  (the Schur complement), so gain = sum_i gain_i + 1/2 [ln det S_after - ln det S_before]:
  ``gain_pixels`` the pixels' part (given the width), ``gain_shared`` the width's.
* Pixels are a random sample of ``max_pixels`` of those with an estimate (the same sample
  for every candidate); sums over pixels are scaled by (pixels with an estimate) /
  (sampled), an unbiased estimate of the full sum. ``share_informed`` is the share of the
  sampled pixels whose own gain (given the shared width) is at least
  :data:`INFORMED_GAIN` (their posterior volume shrinks by 10% or more).

Candidates (:class:`Candidates`): a grid over the hemisphere at the capture's distance
(:func:`hemisphere_candidates`), listed positions (:func:`listed_candidates`) or the
positions of photos of a capture (:func:`photo_candidates`). Every candidate keeps the
capture's flash offset from the lens (the median of light_pos - camera_pos) unless its
light positions are given. A photo is assumed to see the whole sample (rectified).

Where its highlight falls (``highlight``): the point of the plane where the half vector is
the normal, the mirror point x = (C_xy L_z + L_xy C_z) / (C_z + L_z) of camera C and
light L; ``highlight_radius``: where a GGX lobe of the fit's median width falls to half its
peak, z tan(0.644 alpha) (D(h) ~ (alpha^2 + tan^2 theta_h)^-2 near the peak halves at
tan theta_h = alpha sqrt(sqrt(2) - 1)), z the mean height of light and camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import log_ndtr, ndtr

from jaxrefl import fit
from jaxrefl._errors import JaxreflError

from ._data import pixel_take
from ._job import CaptureFit
from ._models import TWO_STAGE, capture_model

__all__ = [
    "INFORMED_GAIN",
    "Candidates",
    "Plan",
    "PlanOptions",
    "censoring_factor",
    "hemisphere_candidates",
    "listed_candidates",
    "photo_candidates",
    "photo_information",
    "plan_next",
]

# A pixel is "informed" by a photo whose gain for it is at least this many nats: its
# posterior volume shrinks by 10% (exp(-gain) = 0.9) or more.
INFORMED_GAIN = -math.log(0.9)
# tan of the half-vector angle, per unit alpha, where a GGX lobe falls to half its peak
# (module docstring): sqrt(sqrt(2) - 1).
_HALF_PEAK = math.sqrt(math.sqrt(2.0) - 1.0)
# Standardised distances to the censoring bounds are clipped here: beyond 30 sigma the
# normal's tail terms are 0 to float64 precision (and inf - inf would make NaN).
_Z_MAX = 30.0


@dataclass(frozen=True)
class PlanOptions:
    """How :func:`plan_next` scores candidates (module docstring).

    max_pixels:  pixels sampled (with an estimate), the same for every candidate; sums are
                 scaled to all pixels with an estimate
    seed:        of that sample
    prior_width: std, in theta units, of the weak prior added to every precision (as
                 :func:`jaxrefl.measured.rank_candidates`)
    censoring:   whether a new observation may saturate or clip dark (the Tobit factor);
                 False scores every observation as uncensored
    """

    max_pixels: int = 4096
    seed: int = 0
    prior_width: float = 3.0
    censoring: bool = True

    def __post_init__(self) -> None:
        if self.max_pixels < 1:
            raise JaxreflError(f"PlanOptions.max_pixels must be >= 1, got {self.max_pixels}")
        if not (math.isfinite(self.prior_width) and self.prior_width > 0):
            raise JaxreflError(
                f"PlanOptions.prior_width must be a finite std > 0, got {self.prior_width}"
            )


@dataclass(frozen=True)
class Candidates:
    """Candidate camera-and-flash positions, in the capture's frame and unit (cm).

    camera_pos, light_pos: (M, 3); light_power: (M, C) the flash's intensity (the
    capture's units); photos: the photo index of each candidate where they are photos of a
    capture (``jaxrefl plan --candidates-from``), else None; kind: ``"grid"``, ``"listed"``
    or ``"photos"``.
    """

    camera_pos: np.ndarray
    light_pos: np.ndarray
    light_power: np.ndarray
    photos: tuple[int, ...] | None = None
    kind: str = "listed"

    def __post_init__(self) -> None:
        cam = np.atleast_2d(np.asarray(self.camera_pos, np.float64))
        light = np.atleast_2d(np.asarray(self.light_pos, np.float64))
        m = cam.shape[0]
        if cam.shape != (m, 3) or light.shape != (m, 3) or m == 0:
            raise JaxreflError(
                f"candidate camera_pos and light_pos must both be (M, 3) with M >= 1, got "
                f"{cam.shape} and {light.shape}"
            )
        if not (np.all(np.isfinite(cam)) and np.all(np.isfinite(light))):
            raise JaxreflError("candidate positions must be finite numbers")
        if np.any(cam[:, 2] <= 0) or np.any(light[:, 2] <= 0):
            raise JaxreflError(
                "candidate camera_pos and light_pos must lie above the sample (z > 0)"
            )
        power = np.asarray(self.light_power, np.float64)
        power = np.broadcast_to(power.reshape(-1, power.shape[-1]) if power.ndim else power, (m, 3))
        if self.photos is not None and len(self.photos) != m:
            raise JaxreflError(f"{len(self.photos)} photo indices for {m} candidates")
        object.__setattr__(self, "camera_pos", cam)
        object.__setattr__(self, "light_pos", light)
        object.__setattr__(self, "light_power", np.array(power))

    def __len__(self) -> int:
        return int(self.camera_pos.shape[0])

    def highlight(self) -> np.ndarray:
        """(M, 2) where each candidate's highlight falls on the plane z = 0 (the mirror point;
        module docstring)."""
        c, lp = self.camera_pos, self.light_pos
        return (c[:, :2] * lp[:, 2:] + lp[:, :2] * c[:, 2:]) / (c[:, 2:] + lp[:, 2:])


def _flash_offset(capture) -> np.ndarray:
    """The capture's flash position relative to the lens (median over photos; 0 for a
    co-located flash)."""
    if capture.light_pos is None:
        raise JaxreflError(
            "capture planning needs a point light (a flash): this capture has directional lights"
        )
    return np.median(capture.light_pos - capture.camera_pos, axis=0)


def _power(capture) -> np.ndarray:
    return np.median(np.asarray(capture.light_power, np.float64), axis=0)


def listed_candidates(capture, camera_pos, light_pos=None) -> Candidates:
    """Candidates at the listed camera positions (M, 3) in the capture's frame; the flash at
    ``light_pos`` (M, 3), or at the capture's offset from the lens; the capture's flash
    intensity."""
    cam = np.atleast_2d(np.asarray(camera_pos, np.float64))
    light = cam + _flash_offset(capture) if light_pos is None else light_pos
    return Candidates(cam, light, _power(capture), kind="listed")


def hemisphere_candidates(
    capture, *, polar_step_deg: float = 7.5, max_polar_deg: float = 45.0
) -> Candidates:
    """A grid over the hemisphere of positions a hand can reach: at the capture's distance
    from the sample's centre (the median over its photos), polar angles 0, step, ... up to
    ``max_polar_deg`` (beyond it a phone sees the sample too obliquely to rectify it
    well), on each ring as many azimuths as keep neighbours about ``polar_step_deg``
    apart. The flash keeps the capture's offset from the lens."""
    if not (0 < polar_step_deg <= max_polar_deg < 90):
        raise JaxreflError(
            f"need 0 < polar_step_deg <= max_polar_deg < 90, got {polar_step_deg}, {max_polar_deg}"
        )
    dist = float(np.median(np.linalg.norm(capture.camera_pos, axis=-1)))
    step = math.radians(polar_step_deg)
    pos = [np.array([0.0, 0.0, dist])]
    for t in np.arange(step, math.radians(max_polar_deg) + 1e-9, step):
        n = max(1, round(2 * math.pi * math.sin(t) / step))
        phi = (np.arange(n) + 0.5 * (round(t / step) % 2)) * 2 * math.pi / n
        ring = np.stack(
            [math.sin(t) * np.cos(phi), math.sin(t) * np.sin(phi), np.full(n, math.cos(t))], -1
        )
        pos.extend(dist * ring)
    cam = np.asarray(pos)
    return Candidates(cam, cam + _flash_offset(capture), _power(capture), kind="grid")


def photo_candidates(capture, photos=None) -> Candidates:
    """The camera and flash positions and flash intensities of ``photos`` (indices, default
    all) of ``capture`` as candidates (e.g. the photos not yet fitted)."""
    k = capture.n_photos
    idx = list(range(k)) if photos is None else [int(i) for i in photos]
    bad = [i for i in idx if not 0 <= i < k]
    if bad or not idx:
        raise JaxreflError(f"candidate photos {bad or idx} out of range: the capture has {k}")
    if capture.light_pos is None:
        raise JaxreflError("capture planning needs a point light (a flash)")
    return Candidates(
        capture.camera_pos[idx],
        capture.light_pos[idx],
        np.asarray(capture.light_power, np.float64)[idx],
        photos=tuple(idx),
        kind="photos",
    )


# ------------------------------------------------------------------------ information
def censoring_factor(mean, std, saturation_level=np.inf, dark_level=-np.inf) -> np.ndarray:
    """lambda in (0, 1]: the Fisher information about the mean of a normal observation
    N(mean, std^2) recorded censored above ``saturation_level`` and below ``dark_level``
    (a Tobit observation), as a share of the uncensored 1 / std^2. With
    a = (dark - mean)/std, b = (sat - mean)/std and phi, Phi the standard normal's density
    and distribution,

        lambda = Phi(b) - Phi(a) - b phi(b) + a phi(a) + phi(b)^2 / (1 - Phi(b))
                 + phi(a)^2 / Phi(a)

    (the expected squared score: the integral of z^2 phi over the uncensored range, and each
    censored outcome's probability times its squared score)."""
    mean = np.asarray(mean, np.float64)
    std = np.asarray(std, np.float64)
    b = np.clip((saturation_level - mean) / std, -_Z_MAX, _Z_MAX)
    a = np.clip((dark_level - mean) / std, -_Z_MAX, _Z_MAX)
    log_phi_b = -0.5 * b * b - 0.5 * math.log(2 * math.pi)
    log_phi_a = -0.5 * a * a - 0.5 * math.log(2 * math.pi)
    inner = ndtr(b) - ndtr(a) - b * np.exp(log_phi_b) + a * np.exp(log_phi_a)
    tails = np.exp(2 * log_phi_b - log_ndtr(-b)) + np.exp(2 * log_phi_a - log_ndtr(a))
    # Round-off can leave a hair outside (0, 1]; the factor is a share of the information.
    return np.clip(inner + tails, 0.0, 1.0)


def photo_information(
    jac, mean, var, saturation_level=np.inf, dark_level=-np.inf, *, censoring: bool = True
) -> np.ndarray:
    """(..., P, P) Fisher information of one photo's observations of a pixel about theta:
    sum_c lambda_c j_c j_c^T / var_c, from the Jacobian ``jac`` (..., C, P) of the predicted
    radiance ``mean`` (..., C) with noise variance ``var`` (..., C), lambda the censoring
    factor (:func:`censoring_factor`; 1 with ``censoring=False``)."""
    jac = np.asarray(jac, np.float64)
    var = np.asarray(var, np.float64)
    lam = (
        censoring_factor(mean, np.sqrt(var), saturation_level, dark_level)
        if censoring
        else np.ones_like(var)
    )
    return np.einsum("...cp,...cq,...c->...pq", jac, jac, lam / var)


def _logdet(a: np.ndarray) -> np.ndarray:
    sign, ld = np.linalg.slogdet(a)
    # A precision that lost positive definiteness to round-off has no volume.
    return np.where(sign > 0, ld, -np.inf)


@eqx.filter_jit
def _residual_jacobian(res, theta, data):
    """(n, rows, P) Jacobian of the fit's residual of every pixel at its theta."""
    return jax.vmap(jax.jacfwd(res))(theta, data)


@eqx.filter_jit
def _prediction_jacobian(model, space, inverse, theta, wi, wo, scale):
    """((n, C, P) Jacobian, (n, C) value) of each pixel's predicted radiance under one new
    photo (directions (n, 3), scale = E cos_i (n, C)); theta's entries in the order whose
    inverse permutation is ``inverse``."""

    def pred(t, wi1, wo1, s1):
        params = space.to_natural(t[inverse][None, :])
        return model.eval(params, wi1[None], wo1[None])[0] * s1

    return jax.vmap(jax.jacfwd(pred))(theta, wi, wo, scale), jax.vmap(pred)(theta, wi, wo, scale)


# ------------------------------------------------------------------------ the fit's state
@dataclass(frozen=True)
class _State:
    """What the plan needs of a fit, on the sampled pixels: the model with its shared
    parameters free, theta (n, P + S), the first P entries per pixel, the last S shared."""

    model: Any
    space: fit.ParamSpace
    noise: fit.NoiseModel
    theta: np.ndarray
    s2: np.ndarray  # (n,) Laplace noise scale
    pixels: np.ndarray  # (n,) row-major indices
    n_est: int  # pixels with an estimate
    n_shared: int
    shared: tuple[str, ...]
    precision: np.ndarray  # (n, P + S, P + S) per pixel, without the weak prior


def _fit_noise(capture_fit: CaptureFit, noise_std: np.ndarray):
    """(noise model of the fit's residual, whether the Laplace step estimated its scale)."""
    job, noise = capture_fit.job, capture_fit.job.config.noise
    pooled = capture_fit.extra.get("pooled")
    unknown = isinstance(noise, fit.GaussianNoise) and noise.sigma is None
    if unknown and pooled is not None and pooled.alpha is not None:
        # An array, not a float: equinox's jit would compile again for every value.
        return fit.GaussianNoise(sigma=jnp.asarray(float(pooled.sigma))), False
    if unknown and job.model in TWO_STAGE:
        # The tilted fit's scale: one value for the capture (empirical Bayes), in the map.
        good = noise_std[np.isfinite(noise_std) & (noise_std > 0)]
        sigma = float(np.median(good)) if good.size else 1.0
        return fit.GaussianNoise(sigma=jnp.asarray(sigma)), False
    return noise, True


def _prior(capture_fit: CaptureFit, space: fit.ParamSpace) -> fit.GaussianPrior | None:
    job, pooled = capture_fit.job, capture_fit.extra.get("pooled")
    if pooled is not None and pooled.alpha is not None:
        chans = [lab.split(".", 1)[1] for lab in space.labels if lab.startswith("specular.")]
        return fit.gaussian_prior(
            space,
            {
                f"specular.{ch}": (mu, sd)
                for ch, mu, sd in zip(chans, pooled.prior_mean, pooled.prior_std, strict=True)
            },
        )
    if job.model in TWO_STAGE:
        t = float(job.tilt_std)
        return fit.gaussian_prior(space, {"tilt_x": (0.0, t), "tilt_y": (0.0, t)})
    return None


def _state(capture_fit: CaptureFit, capture, options: PlanOptions) -> _State:
    model, space = capture_fit.model()
    h, w = capture_fit.maps["status"].shape
    k, hc, wc, c = capture.shape
    if (hc, wc) != (h, w):
        raise JaxreflError(
            f"the capture's photos are {hc} x {wc} pixels, the fit's maps {h} x {w}: give the "
            "capture the fit was made from (same resolution and downsampling)"
        )
    theta_all = np.asarray(capture_fit.theta, np.float64)
    ok = np.all(np.isfinite(theta_all), axis=-1)
    if not np.any(ok):
        raise JaxreflError("the fit has no pixel with an estimate: nothing to plan from")
    est = np.flatnonzero(ok)
    rng = np.random.default_rng(options.seed)
    take = np.sort(rng.choice(est, min(options.max_pixels, est.size), replace=False))
    dtype = capture_fit.job.dtype
    nat = space.to_natural(jnp.asarray(theta_all[take], dtype))
    shared: tuple[str, ...] = ()
    pooled = capture_fit.extra.get("pooled")
    if pooled is not None and pooled.alpha is not None:
        # The shared width becomes a free parameter of the same model (counted once).
        model, space = capture_model(
            "ggx_rgb", c, alpha_min=min(float(capture_fit.extra["alpha_min"]), pooled.alpha)
        )
        shared = ("alpha",)
    theta = np.asarray(space.from_natural(nat, dtype=dtype), np.float64)
    noise_std = np.asarray(capture_fit.maps["noise_std"], np.float64).reshape(-1)
    noise, estimated = _fit_noise(capture_fit, noise_std)
    if estimated:
        s = noise_std[take]
        med = np.median(noise_std[np.isfinite(noise_std) & (noise_std > 0)])
        # A pixel without a noise estimate (n <= P) takes the capture's median scale.
        s = np.where(np.isfinite(s) & (s > 0), s, med if np.isfinite(med) else 1.0)
        s2 = s * s
    else:
        s2 = np.ones(take.size)
    res = fit.make_residual(
        model, space, noise, capture_fit.job.config.loss, _prior(capture_fit, space)
    )
    data = pixel_take(capture, take, dtype=dtype)
    train = np.ones(k)
    train[list(capture_fit.job.holdout)] = 0.0
    data = eqx.tree_at(
        lambda d: d.weight, data, data.weight * jnp.asarray(train, data.weight.dtype)[None, :, None]
    )
    jac = _residual_jacobian(res, jnp.asarray(theta, dtype), data)
    jac = np.asarray(jac, np.float64)
    jac = np.where(np.isfinite(jac), jac, 0.0)  # a non-finite row carries no information
    precision = np.einsum("nrp,nrq->npq", jac, jac) / s2[:, None, None]
    return _State(
        model=model,
        space=space,
        noise=noise,
        theta=_shared_last(space, theta, shared),
        s2=s2,
        pixels=take,
        n_est=int(est.size),
        n_shared=sum(space.index(nm).stop - space.index(nm).start for nm in shared),
        shared=shared,
        precision=_shared_last(space, precision, shared, matrix=True),
    )


def _order(space: fit.ParamSpace, shared: tuple[str, ...]) -> np.ndarray:
    """theta entries with the shared parameters' last."""
    last = [j for n in shared for j in range(space.index(n).start, space.index(n).stop)]
    return np.array([j for j in range(space.size) if j not in last] + last, int)


def _shared_last(space, x, shared, matrix=False):
    o = _order(space, shared)
    return x[:, o][:, :, o] if matrix else x[:, o]


# ------------------------------------------------------------------------ the plan
@dataclass(frozen=True)
class Plan:
    """Candidates ranked by expected information gain (module docstring).

    candidates:     the :class:`Candidates` scored
    gain:           (M,) nats, gain_pixels + gain_shared
    gain_pixels:    (M,) the per-pixel parameters' part (given the shared ones)
    gain_shared:    (M,) the shared parameters' part (0 where none is shared)
    share_informed: (M,) share of pixels whose own gain is >= :data:`INFORMED_GAIN`
    order:          (M,) candidate indices, best first
    highlight:      (M, 2) where each candidate's highlight falls (capture units)
    highlight_radius: (M,) the radius of a lobe of the fit's median width there (0: none)
    pixels_sampled, pixels: pixels scored and pixels with an estimate (sums scaled to them)
    shared:         names of the parameters shared by every pixel
    side:           the sample's side (capture units): a highlight is on the sample where
                    both |x| and |y| are below side / 2
    """

    candidates: Candidates
    gain: np.ndarray
    gain_pixels: np.ndarray
    gain_shared: np.ndarray
    share_informed: np.ndarray
    order: np.ndarray
    highlight: np.ndarray
    highlight_radius: np.ndarray
    pixels_sampled: int
    pixels: int
    shared: tuple[str, ...]
    side: float

    @property
    def best(self) -> int:
        """The recommended next photo (index into the candidates)."""
        return int(self.order[0])

    def ranking(self) -> list[dict[str, Any]]:
        """One dict per candidate, best first: ``photo`` (photo candidates) or ``position``
        (camera position, capture units), ``light_position``, ``gain``, ``gain_pixels``,
        ``gain_shared``, ``share_informed``, ``highlight`` (x, y) and ``highlight_on_sample``."""
        cand = self.candidates
        out = []
        for m in self.order:
            row: dict[str, Any] = {}
            if cand.photos is not None:
                row["photo"] = int(cand.photos[m])
            row["position"] = [float(v) for v in cand.camera_pos[m]]
            row["light_position"] = [float(v) for v in cand.light_pos[m]]
            row["gain"] = float(self.gain[m])
            row["gain_pixels"] = float(self.gain_pixels[m])
            row["gain_shared"] = float(self.gain_shared[m])
            row["share_informed"] = float(self.share_informed[m])
            row["highlight"] = [float(v) for v in self.highlight[m]]
            row["highlight_on_sample"] = bool(np.all(np.abs(self.highlight[m]) <= self.side / 2))
            out.append(row)
        return out


def _candidate_geometry(points: np.ndarray, cam: np.ndarray, light: np.ndarray, power):
    """wi, wo (n, 3) and scale = E cos_i (n, C) of one candidate at ``points`` (n, 3)."""
    d = light - points
    r2 = np.sum(d * d, axis=-1)
    wi = d / np.sqrt(r2)[:, None]
    v = cam - points
    wo = v / np.linalg.norm(v, axis=-1, keepdims=True)
    # Light from below the plane does not reach the surface (as Capture does).
    cos_i = np.maximum(wi[:, 2], 0.0)
    return wi, wo, (power[None, :] / r2[:, None]) * cos_i[:, None]


def plan_next(
    capture_fit: CaptureFit,
    capture,
    candidates: Candidates | None = None,
    options: PlanOptions | None = None,
) -> Plan:
    """Rank ``candidates`` (default: :func:`hemisphere_candidates` of ``capture``) by the
    expected information gain of a photo taken there about the fit's parameters (module
    docstring: the criterion, its linearisation and censoring, the shared parameters, the
    pixel sample).

    capture_fit: a :class:`CaptureFit` (:func:`fit_capture`, or read back from a fit's
                 folder with :func:`jaxrefl.svbrdf.read_fit`)
    capture:     the capture it was fitted to (its geometry, photos and saturation level;
                 the fit's held-out photos are not counted as measured)
    """
    options = PlanOptions() if options is None else options
    candidates = hemisphere_candidates(capture) if candidates is None else candidates
    if candidates.light_power.shape[-1] != capture.shape[-1]:
        raise JaxreflError(
            f"candidate light_power has {candidates.light_power.shape[-1]} channels, the "
            f"capture {capture.shape[-1]}"
        )
    st = _state(capture_fit, capture, options)
    n, q = st.theta.shape
    s = st.n_shared
    p = q - s
    scale_up = st.n_est / n
    eye_p = np.eye(p) / options.prior_width**2
    a_pp = st.precision[:, :p, :p] + eye_p
    ld_before = _logdet(a_pp)
    if s:
        a_ps = st.precision[:, :p, p:]
        schur_before = np.eye(s) / options.prior_width**2 + scale_up * np.sum(
            st.precision[:, p:, p:] - np.swapaxes(a_ps, 1, 2) @ np.linalg.solve(a_pp, a_ps),
            axis=0,
        )
    points = capture.points.reshape(-1, 3)[st.pixels].astype(np.float64)
    dtype = capture_fit.job.dtype
    order = _order(st.space, st.shared)
    inverse = np.argsort(order)
    noise = st.noise
    inverse_j = jnp.asarray(inverse)
    theta_j = jnp.asarray(st.theta, dtype)
    m = len(candidates)
    gain_px, gain_sh, informed = np.zeros(m), np.zeros(m), np.zeros(m)
    for j in range(m):
        wi, wo, sc = _candidate_geometry(
            points, candidates.camera_pos[j], candidates.light_pos[j], candidates.light_power[j]
        )
        jac, mean = _prediction_jacobian(
            st.model,
            st.space,
            inverse_j,
            theta_j,
            jnp.asarray(wi, dtype),
            jnp.asarray(wo, dtype),
            jnp.asarray(sc, dtype),
        )
        jac = np.nan_to_num(np.asarray(jac, np.float64))  # a non-finite row informs nothing
        mean = np.asarray(mean, np.float64)
        std_model = np.asarray(noise.std(jnp.asarray(mean)), np.float64)
        var = st.s2[:, None] * std_model**2
        f = photo_information(
            jac,
            mean,
            var,
            capture.saturation_level,
            capture.dark_level,
            censoring=options.censoring,
        )
        f_pp = f[:, :p, :p]
        g_i = 0.5 * (_logdet(a_pp + f_pp) - ld_before)
        gain_px[j] = scale_up * float(np.sum(g_i))
        informed[j] = float(np.mean(g_i >= INFORMED_GAIN))
        if s:
            a_after = a_pp + f_pp
            b_after = a_ps + f[:, :p, p:]
            c_after = st.precision[:, p:, p:] + f[:, p:, p:]
            schur_after = np.eye(s) / options.prior_width**2 + scale_up * np.sum(
                c_after - np.swapaxes(b_after, 1, 2) @ np.linalg.solve(a_after, b_after), axis=0
            )
            gain_sh[j] = 0.5 * float(_logdet(schur_after[None])[0] - _logdet(schur_before[None])[0])
    gain = gain_px + gain_sh
    alpha = _median_alpha(capture_fit)
    heights = 0.5 * (candidates.camera_pos[:, 2] + candidates.light_pos[:, 2])
    radius = heights * np.tan(_HALF_PEAK * alpha) if alpha is not None else np.zeros(m)
    return Plan(
        candidates=candidates,
        gain=gain,
        gain_pixels=gain_px,
        gain_shared=gain_sh,
        share_informed=informed,
        order=np.argsort(-gain, kind="stable"),
        highlight=candidates.highlight(),
        highlight_radius=radius,
        pixels_sampled=n,
        pixels=st.n_est,
        shared=st.shared,
        side=float(capture.side),
    )


def _median_alpha(capture_fit: CaptureFit) -> float | None:
    a = capture_fit.maps.get("alpha")
    if a is None:
        return None
    a = np.asarray(a, np.float64)
    a = a[np.isfinite(a)]
    return float(np.median(a)) if a.size else None
