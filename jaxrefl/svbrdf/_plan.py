"""Where to take the next photo: candidate camera-and-flash positions ranked by what a
photo there is expected to teach the fit.

Criterion (``PlanOptions.criterion``; all linearised at the fit's theta, Bayesian design,
Chaloner & Verdinelli 1995):

* ``variance`` (the default; V- or I-optimal design, Atkinson, Donev & Tobias 2007, ch.
  10): the expected reduction of the predictive variance of reference renderings, summed
  over pixels, reference renderings and channels, as a share of its current value,

      gain_c = [V(A) - V(A + F_c)] / V(A),   V(A) = sum_r sum_i sum_ch p_r^2 g_r^T A^-1 g_r

  with g_r = dy_r / dtheta the Jacobian of the rendering of pixel i under reference r
  (radiance units, :func:`._plan_info.predictive_variance`) and p_r the slope of the value
  the camera records (:func:`._plan_info.recorded_slope`: the probability that it is not
  censored at the capture's saturation or dark level; 1 with ``censoring=False``): the
  variance is that of the recorded rendering (delta method), so a reference highlight far
  above the saturation level, recorded saturated whatever the parameters, has none to
  reduce, and a candidate is not scored by what it teaches about values no photo records.
  The reference renderings are the candidates themselves (or ``reference``): the views
  and flash positions the capture could have, so the criterion is the expected reduction
  of the squared error with which the fit predicts a photo taken at any of them; it weighs
  each pixel and parameter by how much it changes a rendering, in the units of the photos,
  where the information counts every identified direction of every pixel alike (a nat on
  a dark pixel's albedo the same as on a highlight's width).
* ``log_variance``: the same predictive variance pixel by pixel, V_i(A) (V's terms of pixel
  i, :func:`._plan_info.pixel_predictive_variance`), and the mean over pixels of the log of
  its reduction,

      gain_c = mean_i ln[V_i(A) / V_i(A + F_c)]

  (pixels whose V_i is 0, no reference rendering recorded uncensored, left out). A pixel
  counts by the factor its variance shrinks, as the information counts nats, but only in
  the directions that change its recorded renderings; the share ``variance`` is led by the
  pixels with the largest variance (bright highlights, lobes the photos have not pinned
  down), which suits an error summed over pixels in radiance (held-out RMSE), where
  ``log_variance`` suits an error every pixel counts alike in (a median over the map).
* ``information`` (D-optimal; the capture-wide form of
  :func:`jaxrefl.measured.rank_candidates`): the expected information gain about the
  parameters, gain_c = 1/2 ln det(A + F_c) - 1/2 ln det(A) nats, the mutual information
  between the photo and the parameters (a factor exp(-gain_c) on the posterior's volume).
  It is computed for every criterion (``Plan.information``).

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

  (the Schur complement), so information = sum_i gain_i + 1/2 [ln det S_after - ln det
  S_before]: ``gain_pixels`` the pixels' part (given the width), ``gain_shared`` the
  width's; the predictive variance carries the width's variance S^-1 into every pixel's
  rendering the same way.
* The light: where the fit estimated the flash (``FitJob.light``, the report's ``light``),
  the precision is that of the photos as the fit placed their flash, and candidates with
  the flash where the capture states it get the estimated offset (:mod:`._plan_light`).
* Pixels are a random sample of ``max_pixels`` of those with an estimate (the same sample
  for every candidate); sums over pixels are scaled by (pixels with an estimate) /
  (sampled), an unbiased estimate of the full sum. ``share_informed`` is the share of the
  sampled pixels whose own information gain (given the shared width) is at least
  :data:`INFORMED_GAIN` (their posterior volume shrinks by 10% or more).

What no criterion sees: the model's own error (a bias, e.g. the relief of an embossed
sample that a per-pixel lobe on a flat normal cannot render) is not reduced by any photo,
and the linearisation takes the fit's theta for the truth. A pixel whose lobe no photo has
pinned down often has its width at a bound of the parameter's range, where the bijection
to theta is flat: its Jacobians there are near 0, so no candidate is credited with what it
would teach that pixel (its share of V and of the information is near 0, whatever it
would gain if its lobe were a typical one).

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

import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl._names import PLAN_CRITERIA

from ._job import CaptureFit
from ._plan_info import (
    _candidate_geometry,
    _logdet,
    _order,
    _prediction_jacobian,
    _state,
    censoring_factor,
    photo_information,
    pixel_predictive_variance,
    recorded_slope,
    schur,
)
from ._plan_light import fit_light, orientations, place_flash

__all__ = [
    "CRITERIA",
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
# The criteria of PlanOptions.criterion (module docstring), the default first.
CRITERIA = PLAN_CRITERIA
# tan of the half-vector angle, per unit alpha, where a GGX lobe falls to half its peak
# (module docstring): sqrt(sqrt(2) - 1).
_HALF_PEAK = math.sqrt(math.sqrt(2.0) - 1.0)


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
    criterion:   what ranks the candidates (:data:`CRITERIA`, module docstring):
                 ``variance`` the expected reduction of the reference renderings'
                 predictive variance (a share of the sum over pixels), ``log_variance``
                 the mean over pixels of the log of its reduction, ``information`` the
                 expected information gain
    """

    max_pixels: int = 4096
    seed: int = 0
    prior_width: float = 3.0
    censoring: bool = True
    criterion: str = "variance"

    def __post_init__(self) -> None:
        if self.max_pixels < 1:
            raise JaxreflError(f"PlanOptions.max_pixels must be >= 1, got {self.max_pixels}")
        if not (math.isfinite(self.prior_width) and self.prior_width > 0):
            raise JaxreflError(
                f"PlanOptions.prior_width must be a finite std > 0, got {self.prior_width}"
            )
        if self.criterion not in CRITERIA:
            raise JaxreflError(
                f"PlanOptions.criterion must be one of {', '.join(CRITERIA)}, not "
                f"{self.criterion!r}"
            )


@dataclass(frozen=True)
class Candidates:
    """Candidate camera-and-flash positions, in the capture's frame and unit (cm).

    camera_pos, light_pos: (M, 3); light_power: (M, C) the flash's intensity (the
    capture's units); photos: the photo index of each candidate where they are photos of a
    capture (``jaxrefl plan --candidates-from``), else None; kind: ``"grid"``, ``"listed"``
    or ``"photos"``; flash: ``"stated"`` where the flash is where the capture states it
    (moved by a fit's estimated light, :mod:`._plan_light`), ``"placed"`` where it is
    given; orientation: (M, 3, 3) camera-to-sample rotations of photo candidates where the
    capture gives them (the frame of an estimated flash offset), else None.
    """

    camera_pos: np.ndarray
    light_pos: np.ndarray
    light_power: np.ndarray
    photos: tuple[int, ...] | None = None
    kind: str = "listed"
    flash: str = "stated"
    orientation: np.ndarray | None = None

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
        if self.flash not in ("stated", "placed"):
            raise JaxreflError(f"Candidates.flash must be 'stated' or 'placed', not {self.flash!r}")
        if self.orientation is not None and np.shape(self.orientation) != (m, 3, 3):
            raise JaxreflError(
                f"Candidates.orientation must be (M, 3, 3), got {np.shape(self.orientation)}"
            )
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
    if light_pos is None:
        return Candidates(cam, cam + _flash_offset(capture), _power(capture), kind="listed")
    return Candidates(cam, light_pos, _power(capture), kind="listed", flash="placed")


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
    rot = orientations(capture)
    return Candidates(
        capture.camera_pos[idx],
        capture.light_pos[idx],
        np.asarray(capture.light_power, np.float64)[idx],
        photos=tuple(idx),
        kind="photos",
        orientation=None if rot is None else rot[idx],
    )


# ------------------------------------------------------------------------ the plan
@dataclass(frozen=True)
class Plan:
    """Candidates ranked by the criterion (module docstring).

    candidates:     the :class:`Candidates` scored (with the fit's flash where it placed one)
    criterion:      the ranking's (:data:`CRITERIA`)
    gain:           (M,) the criterion's score: ``variance`` the share of the reference
                    renderings' predictive variance a photo there is expected to remove,
                    ``information`` nats
    variance_reduction: (M,) that share, for every criterion
    log_variance_reduction: (M,) the mean over pixels of ln(V_i before / V_i after), for
                    every criterion
    information:    (M,) nats, gain_pixels + gain_shared
    gain_pixels:    (M,) the information's per-pixel part (given the shared parameters)
    gain_shared:    (M,) the shared parameters' part (0 where none is shared)
    share_informed: (M,) share of pixels whose own information gain is >= :data:`INFORMED_GAIN`
    order:          (M,) candidate indices, best first
    highlight:      (M, 2) where each candidate's highlight falls (capture units)
    highlight_radius: (M,) the radius of a lobe of the fit's median width there (0: none)
    pixels_sampled, pixels: pixels scored and pixels with an estimate (sums scaled to them)
    shared:         names of the parameters shared by every pixel
    side:           the sample's side (capture units): a highlight is on the sample where
                    both |x| and |y| are below side / 2
    light:          the fit's light mode the plan used (``fixed``: as the capture states)
    """

    candidates: Candidates
    criterion: str
    gain: np.ndarray
    variance_reduction: np.ndarray
    log_variance_reduction: np.ndarray
    information: np.ndarray
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
    light: str = "fixed"

    @property
    def best(self) -> int:
        """The recommended next photo (index into the candidates)."""
        return int(self.order[0])

    def ranking(self) -> list[dict[str, Any]]:
        """One dict per candidate, best first: ``photo`` (photo candidates) or ``position``
        (camera position, capture units), ``light_position``, ``gain`` (the criterion's),
        ``variance_reduction``, ``log_variance_reduction``, ``information``,
        ``gain_pixels``, ``gain_shared``,
        ``share_informed``, ``highlight`` (x, y) and ``highlight_on_sample``."""
        cand = self.candidates
        out = []
        for m in self.order:
            row: dict[str, Any] = {}
            if cand.photos is not None:
                row["photo"] = int(cand.photos[m])
            row["position"] = [float(v) for v in cand.camera_pos[m]]
            row["light_position"] = [float(v) for v in cand.light_pos[m]]
            row["gain"] = float(self.gain[m])
            row["variance_reduction"] = float(self.variance_reduction[m])
            row["log_variance_reduction"] = float(self.log_variance_reduction[m])
            row["information"] = float(self.information[m])
            row["gain_pixels"] = float(self.gain_pixels[m])
            row["gain_shared"] = float(self.gain_shared[m])
            row["share_informed"] = float(self.share_informed[m])
            row["highlight"] = [float(v) for v in self.highlight[m]]
            row["highlight_on_sample"] = bool(np.all(np.abs(self.highlight[m]) <= self.side / 2))
            out.append(row)
        return out


def plan_next(
    capture_fit: CaptureFit,
    capture,
    candidates: Candidates | None = None,
    options: PlanOptions | None = None,
    reference: Candidates | None = None,
) -> Plan:
    """Rank ``candidates`` (default: :func:`hemisphere_candidates` of ``capture``) by what a
    photo taken there is expected to teach the fit (module docstring: the criteria, their
    linearisation and censoring, the shared parameters, the light, the pixel sample).

    capture_fit: a :class:`CaptureFit` (:func:`fit_capture`, or read back from a fit's
                 folder with :func:`jaxrefl.svbrdf.read_fit`)
    capture:     the capture it was fitted to (its geometry, photos and saturation level;
                 the fit's held-out photos are not counted as measured), its flash as
                 stated: an estimated light of the fit is applied here
    reference:   the renderings whose predictive variance the ``variance`` criterion
                 reduces (default: the candidates)
    """
    options = PlanOptions() if options is None else options
    light = fit_light(capture_fit, capture)
    train = np.ones(capture.n_photos, bool)
    train[[i for i in capture_fit.job.holdout if 0 <= i < capture.n_photos]] = False
    if light is not None:
        capture = light.apply(capture)
    candidates = hemisphere_candidates(capture) if candidates is None else candidates
    candidates = place_flash(candidates, light, capture, train)
    reference = candidates if reference is None else place_flash(reference, light, capture, train)
    for what, c in (("candidate", candidates), ("reference", reference)):
        if c.light_power.shape[-1] != capture.shape[-1]:
            raise JaxreflError(
                f"{what} light_power has {c.light_power.shape[-1]} channels, the capture "
                f"{capture.shape[-1]}"
            )
    st = _state(capture_fit, capture, options.max_pixels, options.seed)
    n, q = st.theta.shape
    s = st.n_shared
    p = q - s
    scale_up = st.n_est / n
    tau = 1.0 / options.prior_width**2
    a_pp = st.precision[:, :p, :p] + np.eye(p) * tau
    a_ps, a_ss = st.precision[:, :p, p:], st.precision[:, p:, p:]
    ld_before = _logdet(a_pp)
    if s:
        schur_before = _logdet(schur(a_pp, a_ps, a_ss, tau, scale_up)[None])[0]
    points = capture.points.reshape(-1, 3)[st.pixels].astype(np.float64)
    dtype = capture_fit.job.dtype
    inverse = jnp.asarray(np.argsort(_order(st.space, st.shared)))
    theta_j = jnp.asarray(st.theta, dtype)

    sat, dark = capture.saturation_level, capture.dark_level

    def photo(c: Candidates, j: int):
        """(Jacobian (n, C, q), predicted radiance (n, C), noise variance (n, C)) of a photo
        at c[j]."""
        wi, wo, sc = _candidate_geometry(points, c.camera_pos[j], c.light_pos[j], c.light_power[j])
        args = (jnp.asarray(wi, dtype), jnp.asarray(wo, dtype), jnp.asarray(sc, dtype))
        jac, mean = _prediction_jacobian(st.model, st.space, inverse, theta_j, *args)
        jac = np.nan_to_num(np.asarray(jac, np.float64))  # a non-finite row informs nothing
        mean = np.asarray(mean, np.float64)
        var = st.s2[:, None] * np.asarray(st.noise.std(jnp.asarray(mean)), np.float64) ** 2
        return jac, mean, var

    moment = np.zeros((n, q, q))
    for j in range(len(reference)):
        g, mean, var = photo(reference, j)
        # The reference rendering as the camera records it (censored at its levels).
        w = recorded_slope(mean, np.sqrt(var), sat, dark) ** 2 if options.censoring else 1.0
        moment += np.einsum("ncp,ncq,nc->npq", g, g, np.broadcast_to(w, mean.shape))
    v_px_before = pixel_predictive_variance(a_pp, a_ps, a_ss, moment, tau, scale_up)
    v_before = scale_up * float(np.sum(v_px_before))
    # A pixel none of whose reference renderings is recorded uncensored has no variance to
    # reduce: it is left out of the log ratio (0 / 0).
    seen = v_px_before > 0
    m = len(candidates)
    gain_px, gain_sh, informed, v_red = np.zeros(m), np.zeros(m), np.zeros(m), np.zeros(m)
    log_red = np.zeros(m)
    for j in range(m):
        jac, mean, var = photo(candidates, j)
        f = photo_information(jac, mean, var, sat, dark, censoring=options.censoring)
        a_after = a_pp + f[:, :p, :p]
        b_after, c_after = a_ps + f[:, :p, p:], a_ss + f[:, p:, p:]
        g_i = 0.5 * (_logdet(a_after) - ld_before)
        gain_px[j] = scale_up * float(np.sum(g_i))
        informed[j] = float(np.mean(g_i >= INFORMED_GAIN))
        if s:
            after = _logdet(schur(a_after, b_after, c_after, tau, scale_up)[None])[0]
            gain_sh[j] = 0.5 * float(after - schur_before)
        v_px = pixel_predictive_variance(a_after, b_after, c_after, moment, tau, scale_up)
        v_after = scale_up * float(np.sum(v_px))
        v_red[j] = (v_before - v_after) / v_before if v_before > 0 else 0.0
        if np.any(seen):
            log_red[j] = float(np.mean(np.log(v_px_before[seen] / v_px[seen])))
    info = gain_px + gain_sh
    gain = {"variance": v_red, "log_variance": log_red, "information": info}[options.criterion]
    alpha = _median_alpha(capture_fit)
    heights = 0.5 * (candidates.camera_pos[:, 2] + candidates.light_pos[:, 2])
    radius = heights * np.tan(_HALF_PEAK * alpha) if alpha is not None else np.zeros(m)
    return Plan(
        candidates=candidates,
        criterion=options.criterion,
        gain=gain,
        variance_reduction=v_red,
        log_variance_reduction=log_red,
        information=info,
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
        light="fixed" if light is None else light.mode,
    )


def _median_alpha(capture_fit: CaptureFit) -> float | None:
    a = capture_fit.maps.get("alpha")
    if a is None:
        return None
    a = np.asarray(a, np.float64)
    a = a[np.isfinite(a)]
    return float(np.median(a)) if a.size else None
