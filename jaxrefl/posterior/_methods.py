"""Per-pixel uncertainty method codes, as stored in the ``method`` channel of
``uncertainty.exr`` and in ``report.json`` (``method_codes``). The numbers are stored and never
change; compare codes through :class:`Method`, never as bare numbers."""

from __future__ import annotations

import enum

__all__ = ["MCMC_METHODS", "Method"]


class Method(enum.IntEnum):
    """How a pixel's uncertainty was computed (:data:`jaxrefl.posterior.METHODS` names them)."""

    NONE = 0  # no estimate (the fit has none)
    LAPLACE = 1  # the Laplace approximation was trusted
    MCMC = 2  # sampled because the Laplace approximation was not reliable
    MCMC_AUDIT = 3  # sampled to audit a reliable Laplace approximation
    # chosen for MCMC, but the map's time limit left it its Laplace summary
    LAPLACE_TIME_LIMIT = 4


#: The codes of pixels that were sampled (by MCMC).
MCMC_METHODS: tuple[Method, ...] = (Method.MCMC, Method.MCMC_AUDIT)
