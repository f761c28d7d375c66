"""Polar plots of measured against fitted lobes in the plane of incidence.

For an incidence angle theta_i the plane of incidence holds the normal and wi; an outgoing
direction in it is drawn at the signed angle +theta_o on the mirror side (azimuth opposite
to wi's) and -theta_o on the side of the light. Measured samples are those with theta_i
within ``tol_deg`` of the chosen angle and wo within ``tol_deg`` of the plane; a tabulated
source (a MERL file: ``meta["table_model"]``) is drawn as a curve instead. Plotted value:
f_r cos(theta_o) averaged over channels, on a log radius covering ``decades`` decades below
the largest measured value at that incidence (the highlight and the diffuse part both show).
Matplotlib is imported lazily.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxrefl.io import MeasuredBRDF

from ._fit import FitReport, predict
from ._retry import x64

__all__ = ["in_plane_samples", "incidence_angles", "plot_fit_lobes"]


def _plane_basis(phi_i: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors along wi's azimuth (in the surface) and across the plane of incidence."""
    along = np.array([np.cos(phi_i), np.sin(phi_i), 0.0])
    across = np.array([-np.sin(phi_i), np.cos(phi_i), 0.0])
    return along, across


def in_plane_samples(
    measured: MeasuredBRDF, theta_i_deg: float, tol_deg: float = 2.5
) -> tuple[np.ndarray, np.ndarray, float]:
    """(signed theta_o in degrees, f_r cos theta_o averaged over channels, mean phi_i) of
    the samples near ``theta_i_deg`` and near the plane of incidence (module docstring)."""
    wi, wo = measured.wi, measured.wo
    th_i = np.degrees(np.arccos(np.clip(wi[:, 2], -1.0, 1.0)))
    near = np.abs(th_i - theta_i_deg) <= tol_deg
    if not np.any(near):
        return np.zeros(0), np.zeros(0), 0.0
    # Azimuth of the light: mean over the chosen samples (x-z plane at normal incidence).
    xy = wi[near, :2].sum(axis=0)
    phi_i = float(np.arctan2(xy[1], xy[0])) if np.hypot(*xy) > 1e-9 else 0.0
    along, across = _plane_basis(phi_i)
    out_of_plane = np.abs(wo @ across)
    sel = near & (out_of_plane <= np.sin(np.deg2rad(tol_deg)))
    th_o = np.degrees(np.arccos(np.clip(wo[sel, 2], -1.0, 1.0)))
    signed = np.where(wo[sel] @ along <= 0.0, th_o, -th_o)
    v = np.nanmean(measured.values[sel], axis=-1) * wo[sel, 2]
    order = np.argsort(signed)
    return signed[order], v[order], phi_i


def incidence_angles(
    measured: MeasuredBRDF, count: int = 4, min_samples: int = 4, tol_deg: float = 2.5
) -> list[float]:
    """Up to ``count`` incidence angles (degrees, rounded) spread over the data, each with at
    least ``min_samples`` samples within ``tol_deg`` of it and of the plane of incidence;
    fixed angles for a tabulated source."""
    if "table_model" in measured.meta:
        return [15.0, 35.0, 55.0, 75.0][:count]
    th = np.unique(np.round(np.degrees(np.arccos(np.clip(measured.wi[:, 2], -1, 1)))))
    good = [
        float(t) for t in th if len(in_plane_samples(measured, float(t), tol_deg)[0]) >= min_samples
    ]
    # Neighbours closer than the tolerance would show the same samples twice.
    spread: list[float] = []
    for t in good:
        if not spread or t - spread[-1] > tol_deg:
            spread.append(t)
    if len(spread) <= count:
        return spread
    idx = np.round(np.linspace(0, len(spread) - 1, count)).astype(int)
    return [spread[i] for i in idx]


def _auto_angles(measured: MeasuredBRDF, count: int = 4) -> tuple[list[float], float]:
    """Angles and the smallest tolerance (2.5, 5 or 10 degrees) giving at least two of them
    (scattered geometries such as CURET's have few exactly in-plane samples)."""
    for tol in (2.5, 5.0, 10.0):
        angles = incidence_angles(measured, count, tol_deg=tol)
        if len(angles) >= min(2, count):
            return angles, tol
    return [15.0, 35.0, 55.0, 75.0][:count], 10.0


def _plane_directions(theta_i_deg: float, phi_i: float, n: int = 361):
    along, _ = _plane_basis(phi_i)
    t = np.deg2rad(np.linspace(-89.0, 89.0, n))
    # +theta_o on the mirror side: the horizontal part points against wi's azimuth.
    wo = np.sin(t)[:, None] * (-along)[None, :] + np.cos(t)[:, None] * np.array([0, 0, 1.0])
    ti = np.deg2rad(theta_i_deg)
    wi = np.sin(ti) * along + np.cos(ti) * np.array([0, 0, 1.0])
    return np.degrees(t), np.broadcast_to(wi, wo.shape).copy(), wo


def _radius(v: np.ndarray, top: float, decades: float) -> np.ndarray:
    # Floor at `decades` below the top: log of 0 (dark or masked samples) has no radius.
    floor = top * 10.0 ** (-decades)
    return np.log10(np.maximum(v, floor) / floor)


def plot_fit_lobes(
    report: FitReport,
    thetas_deg: Sequence[float] | None = None,
    models: Sequence[str] | None = None,
    decades: float = 3.0,
    tol_deg: float | None = None,
) -> Any:
    """One row of polar plots per model, one column per incidence angle: measured samples
    (black dots, or a black curve for a tabulated source) against the fitted lobe.

    ``thetas_deg`` default: spread over the data (:func:`incidence_angles`); ``tol_deg``
    default: the smallest of 2.5, 5 and 10 degrees that finds in-plane samples.
    """
    import matplotlib.pyplot as plt

    measured = report.measured
    names = list(report.fits) if models is None else list(models)
    auto, auto_tol = _auto_angles(measured)
    thetas = list(auto if thetas_deg is None else thetas_deg)
    tol_deg = auto_tol if tol_deg is None else tol_deg
    table = measured.meta.get("table_model")
    fig, axes = plt.subplots(
        len(names),
        len(thetas),
        subplot_kw={"projection": "polar"},
        figsize=(2.6 * len(thetas), 2.5 * len(names) + 0.6),
        squeeze=False,
    )
    for col, th in enumerate(thetas):
        th_s, v_s, phi_i = in_plane_samples(measured, th, tol_deg)
        t_deg, wi, wo = _plane_directions(th, phi_i)
        ref = None
        if table is not None:
            with x64():
                f = table.eval({}, jnp.asarray(wi), jnp.asarray(wo))
            ref = np.asarray(f, dtype=np.float64).mean(axis=-1) * wo[:, 2]
        top_vals = [v_s[np.isfinite(v_s)]] + ([ref] if ref is not None else [])
        top = max((float(np.max(x)) for x in top_vals if x.size), default=1.0)
        top = top if top > 0 else 1.0
        for row, name in enumerate(names):
            ax = axes[row, col]
            fitted = report.fits[name]
            f_hat = predict(fitted.result, wi, wo, fitted.channels).mean(axis=-1) * wo[:, 2]
            if ref is not None:
                ax.plot(np.deg2rad(t_deg), _radius(ref, top, decades), "k-", lw=1.0)
            if th_s.size:
                ax.plot(np.deg2rad(th_s), _radius(v_s, top, decades), "k.", ms=3)
            ax.plot(np.deg2rad(t_deg), _radius(f_hat, top, decades), "-", color="C3", lw=1.2)
            ax.set_theta_zero_location("N")
            ax.set_theta_direction(-1)  # +theta_o (the mirror side) to the right
            ax.set_thetamin(-90)
            ax.set_thetamax(90)
            ax.set_ylim(0, decades)
            ax.set_yticklabels([])
            if row == 0:
                ax.set_title(f"θi = {th:g}°", fontsize=9)
            if col == 0:
                ax.text(-0.25, 0.5, name, transform=ax.transAxes, rotation=90, va="center",
                        ha="center", fontsize=8)  # fmt: skip
    fig.suptitle(
        f"{measured.name}: measured (black, within ±{tol_deg:g}°) vs fitted (red), "
        f"f_r·cos θo in the plane of incidence, log radius over {decades:g} decades",
        fontsize=9,
    )
    fig.tight_layout()
    return fig
