"""MERL tabulated isotropic BRDFs (Matusik, Pfister, Brand, McMillan, "A Data-Driven
Reflectance Model", SIGGRAPH 2003), looked up as in MERL's ``BRDFRead.cpp``.

The table holds f_r in 1/sr (RGB, no cosine) on a grid of Rusinkiewicz half/difference
angles (:mod:`._rusinkiewicz`), shape ``(3, 90, 90, 180)`` = (channel, θh, θd, φd):

* θh index  i = floor(sqrt(θh / (π/2)) * 90)    (non-linear: dense near the highlight)
* θd index  j = floor(θd / (π/2) * 90)
* φd index  k = floor(φd / π * 180), after φd += π where φd < 0 (reciprocity + isotropy
  make f_r π-periodic in φd, so only [0, π) is stored)

each clamped to the table (``BRDFRead.cpp``'s ``theta_half_index``, ``theta_diff_index``,
``phi_diff_index``; θh <= 0 -> 0). φh is ignored (isotropy). The cell (i, j, k) covers
[i, i+1) x [j, j+1) x [k, k+1) in these index coordinates; its *centre* is
θh = ((i + 1/2)/90)² π/2, θd = (j + 1/2)/90 π/2, φd = (k + 1/2)/180 π.

Lookup is nearest-cell (the ``BRDFRead.cpp`` behaviour) or, with ``interpolation=
"trilinear"``, trilinear in index coordinates between cell centres (periodic in φd,
clamped at the θ ends), which equals the cell value at every cell centre.

Missing data: MERL marks cells without measurements (grazing geometries where wi or wo
lies below the horizon) with negative numbers. Lookups return 0 there, not NaN (NaN
would poison every sum and gradient it touches); :meth:`MERL.valid` says where the
nearest cell is a real measurement. Trilinear lookup averages only the valid corners,
renormalising their weights (0 if none is valid).

Gradients with respect to wi and wo are 0 for nearest-cell lookup (piecewise constant)
and piecewise-constant slopes for trilinear; both finite. The model has no parameters:
``params == ()``, call it as ``m.eval({}, wi, wo)``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxrefl._errors import JaxreflError

from ._base import BRDF, Param, Params
from ._frame import safe_sqrt, upper_hemisphere
from ._rusinkiewicz import from_half_diff, to_half_diff

__all__ = ["MERL", "MERL_SCALE", "MERL_SHAPE"]

N_THETA_H, N_THETA_D, N_PHI_D = 90, 90, 180
MERL_SHAPE = (3, N_THETA_H, N_THETA_D, N_PHI_D)
#: Raw-to-f_r factors of BRDFRead.cpp (RED_SCALE, GREEN_SCALE, BLUE_SCALE).
MERL_SCALE = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)

_HALF_PI = 0.5 * np.pi


def _continuous_index(
    theta_h: Float[Array, " *b"], theta_d: Float[Array, " *b"], phi_d: Float[Array, " *b"]
) -> tuple[Float[Array, " *b"], Float[Array, " *b"], Float[Array, " *b"]]:
    """Index coordinates (uh, ud, up) before truncation, as BRDFRead.cpp computes them.

    θh is guarded at 0 (``theta_h <= 0 -> 0`` in BRDFRead.cpp): sqrt has an infinite slope
    there. up is the reciprocity-folded φd in [0, 180].
    """
    uh = safe_sqrt((theta_h / _HALF_PI * N_THETA_H) * N_THETA_H)
    ud = theta_d / _HALF_PI * N_THETA_D
    # Reciprocity: f_r(φd) == f_r(φd + π); BRDFRead.cpp folds φd < 0 up by π.
    phi_d = jnp.where(phi_d < 0, phi_d + jnp.pi, phi_d)
    up = phi_d / jnp.pi * N_PHI_D
    return uh, ud, up


class MERL(BRDF):
    """A MERL-format tabulated BRDF (RGB, f_r in 1/sr); no parameters.

    ``table`` has shape ``(3, 90, 90, 180)`` = (channel, θh, θd, φd), already scaled to
    f_r (``jaxrefl.io.read_merl`` applies the MERL scale factors); negative entries are
    missing data. Reciprocal by construction (the table is indexed by the folded φd),
    not guaranteed energy conserving (measured data can exceed albedo 1 by noise).
    """

    table: Float[Array, "3 90 90 180"]
    interpolation: str = eqx.field(static=True)

    def __init__(self, table: Float[ArrayLike, "3 90 90 180"], interpolation: str = "nearest"):
        table = jnp.asarray(table)
        if table.shape != MERL_SHAPE:
            raise JaxreflError(f"MERL table must have shape {MERL_SHAPE}, got {table.shape}")
        if not jnp.issubdtype(table.dtype, jnp.floating):
            table = table.astype(jnp.result_type(float))
        if interpolation not in ("nearest", "trilinear"):
            raise JaxreflError(
                f"interpolation must be 'nearest' or 'trilinear', got {interpolation!r}"
            )
        self.table = table
        self.interpolation = interpolation

    @property
    def params(self) -> tuple[Param, ...]:
        return ()

    @property
    def reciprocal(self) -> bool:
        return True

    @property
    def energy_conserving(self) -> bool:
        return False

    # ------------------------------------------------------------------ lookups
    def cell_index(
        self, wi: Float[ArrayLike, "*b 3"], wo: Float[ArrayLike, "*b 3"]
    ) -> tuple[Int[Array, " *b"], Int[Array, " *b"], Int[Array, " *b"]]:
        """(i, j, k): the nearest cell, exactly as BRDFRead.cpp's ``lookup_brdf_val``."""
        wi = jnp.asarray(wi)
        theta_h, _, theta_d, phi_d = to_half_diff(wi, jnp.asarray(wo, dtype=wi.dtype))
        uh, ud, up = _continuous_index(theta_h, theta_d, phi_d)
        # C's (int) cast truncates; all coordinates are >= 0 here, so floor is the same.
        # Clamps: θh = π/2, θd = π/2 and φd = π land one past the last cell.
        i = jnp.clip(jnp.floor(uh).astype(jnp.int32), 0, N_THETA_H - 1)
        j = jnp.clip(jnp.floor(ud).astype(jnp.int32), 0, N_THETA_D - 1)
        k = jnp.clip(jnp.floor(up).astype(jnp.int32), 0, N_PHI_D - 1)
        return i, j, k

    def valid(
        self, wi: Float[ArrayLike, "*b 3"], wo: Float[ArrayLike, "*b 3"]
    ) -> Bool[Array, " *b"]:
        """True where both directions are above the horizon and the nearest cell holds a
        measurement in every channel (no negative entry)."""
        wi = jnp.asarray(wi)
        wo = jnp.asarray(wo, dtype=wi.dtype)
        i, j, k = self.cell_index(wi, wo)
        cell = self.table[:, i, j, k]
        return upper_hemisphere(wi, wo) & jnp.all(cell >= 0, axis=0)

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b 3"]:
        if self.interpolation == "trilinear":
            f = self._trilinear(wi, wo)
        else:
            i, j, k = self.cell_index(wi, wo)
            cell = self.table[:, i, j, k]
            # Missing cells (negative) read as 0, see the module docstring.
            f = jnp.where(cell >= 0, cell, 0.0)
        return jnp.moveaxis(f, 0, -1).astype(wi.dtype)

    def _trilinear(self, wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]) -> Array:
        theta_h, _, theta_d, phi_d = to_half_diff(wi, wo)
        uh, ud, up = _continuous_index(theta_h, theta_d, phi_d)
        # Cell values sit at centres (index + 1/2). Clamps: beyond the first/last centre in
        # θ the value is held constant (no data to extrapolate from).
        uh = jnp.clip(uh - 0.5, 0.0, N_THETA_H - 1.0)
        ud = jnp.clip(ud - 0.5, 0.0, N_THETA_D - 1.0)
        up = up - 0.5  # periodic in φd with period 180 cells: no clamp, wrap below
        i0 = jnp.minimum(jnp.floor(uh), N_THETA_H - 2.0)
        j0 = jnp.minimum(jnp.floor(ud), N_THETA_D - 2.0)
        k0 = jnp.floor(up)
        th, td, tp = uh - i0, ud - j0, up - k0
        i0, j0, k0 = i0.astype(jnp.int32), j0.astype(jnp.int32), k0.astype(jnp.int32)
        num = jnp.zeros((3, *uh.shape), dtype=wi.dtype)
        den = jnp.zeros(uh.shape, dtype=wi.dtype)
        for di, wh_ in ((0, 1.0 - th), (1, th)):
            for dj, wd_ in ((0, 1.0 - td), (1, td)):
                for dk, wp_ in ((0, 1.0 - tp), (1, tp)):
                    cell = self.table[:, i0 + di, j0 + dj, (k0 + dk) % N_PHI_D].astype(wi.dtype)
                    ok = jnp.all(cell >= 0, axis=0)
                    w = jnp.where(ok, wh_ * wd_ * wp_, 0.0)
                    num = num + w[None] * jnp.where(cell >= 0, cell, 0.0)
                    den = den + w
        # No valid corner: missing data reads as 0 (den_safe avoids 0/0 in the gradient).
        has = den > 0
        den_safe = jnp.where(has, den, 1.0)
        return jnp.where(has[None], num / den_safe[None], 0.0)

    # ------------------------------------------------------------------ building tables
    @staticmethod
    def cell_angles(dtype=None) -> tuple[Array, Array, Array]:
        """(θh, θd, φd) at the cell centres, each of shape (90, 90, 180), radians."""
        dtype = dtype or jnp.result_type(float)
        i = (jnp.arange(N_THETA_H, dtype=dtype) + 0.5) / N_THETA_H
        j = (jnp.arange(N_THETA_D, dtype=dtype) + 0.5) / N_THETA_D
        k = (jnp.arange(N_PHI_D, dtype=dtype) + 0.5) / N_PHI_D
        theta_h = (i * i * _HALF_PI)[:, None, None]
        theta_d = (j * _HALF_PI)[None, :, None]
        phi_d = (k * jnp.pi)[None, None, :]
        shape = (N_THETA_H, N_THETA_D, N_PHI_D)
        return (
            jnp.broadcast_to(theta_h, shape),
            jnp.broadcast_to(theta_d, shape),
            jnp.broadcast_to(phi_d, shape),
        )

    @staticmethod
    def cell_directions(dtype=None) -> tuple[Array, Array]:
        """(wi, wo) at the cell centres with φh = 0, each (90, 90, 180, 3). Some lie below
        the horizon (z <= 0): those cells can hold no measurement."""
        theta_h, theta_d, phi_d = MERL.cell_angles(dtype)
        return from_half_diff(theta_h, jnp.zeros_like(theta_h), theta_d, phi_d)

    @classmethod
    def from_brdf(
        cls, model: BRDF, params: Params, interpolation: str = "nearest", dtype=None
    ) -> MERL:
        """Tabulate an analytic (isotropic, reciprocal, 3-channel) model at the cell centres;
        cells whose centre lies below the horizon are marked missing (-1), as in MERL."""
        return cls(_tabulate(model, params, dtype), interpolation=interpolation)


@eqx.filter_jit
def _tabulate(model: BRDF, params: Params, dtype) -> Array:
    wi, wo = MERL.cell_directions(dtype)
    f = jnp.broadcast_to(model.eval(params, wi, wo), (*wi.shape[:-1], 3))
    ok = upper_hemisphere(wi, wo)
    # -1 marks a missing cell, as in the MERL files.
    return jnp.moveaxis(jnp.where(ok[..., None], f, -1.0), -1, 0)
