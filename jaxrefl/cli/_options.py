"""Command-line flags to the fit's option objects: the one place strings pick objects.

``--backend`` names a solver (``lean``: :class:`~jaxrefl.fit.LMOptions`, ``optimistix``:
:class:`~jaxrefl.fit.OptimistixLM`, ``jaxopt``: :class:`~jaxrefl.fit.JaxoptLM`) and
``--max-iters`` its iteration budget (default: the solver's own); ``--noise`` names a noise
model (``gaussian``: :class:`~jaxrefl.fit.GaussianNoise`, sigma unknown unless given;
``shot``: :class:`~jaxrefl.fit.ShotNoise`, read and gain 0.002 each unless given, linear
radiance units); ``--loss`` a robust loss (``l2``, ``huber``, ``cauchy``; none
given: the library's default); ``--dtype`` the computation dtype (``float32``,
``float64``).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from jaxrefl._errors import JaxreflError

if TYPE_CHECKING:
    from jaxrefl import fit

__all__ = [
    "BACKENDS",
    "DTYPES",
    "LOSSES",
    "NOISES",
    "OPTIONAL_BACKENDS",
    "SHOT_GAIN",
    "SHOT_READ",
    "fit_config",
    "loss_from_flag",
    "noise_from_flags",
    "solver_from_flags",
]

# Names only: jaxrefl.fit (and JAX) is imported when a command runs, not to build the parser.
BACKENDS = ("lean", "optimistix", "jaxopt")
LOSSES = ("l2", "huber", "cauchy")
NOISES = ("gaussian", "shot")
DTYPES = ("float32", "float64")
SHOT_READ = 0.002  # --read's default: read-noise std, linear radiance units
SHOT_GAIN = 0.002  # --gain's default: radiance units per photo-electron


#: Backends that need an optional package (``pip install 'jaxrefl[backends]'``).
OPTIONAL_BACKENDS = {"optimistix": "optimistix", "jaxopt": "jaxopt"}


def solver_from_flags(backend: str, max_iters: int | None = None) -> fit.Solver:
    """The solver ``--backend`` names, with ``--max-iters`` (None: the solver's default);
    a ``ValueError`` saying what to install when its optional package is missing."""
    import importlib.util

    from jaxrefl import fit

    package = OPTIONAL_BACKENDS.get(backend)
    if package is not None and importlib.util.find_spec(package) is None:
        raise JaxreflError(
            f"--backend {backend} needs the {package} package: pip install 'jaxrefl[backends]'"
        )

    kinds: dict[str, type[fit.Solver]] = {
        "lean": fit.LMOptions,
        "optimistix": fit.OptimistixLM,
        "jaxopt": fit.JaxoptLM,
    }
    solver = kinds[backend]()
    if max_iters is not None:
        solver = dataclasses.replace(solver, max_iters=int(max_iters))
    return solver


def noise_from_flags(
    noise: str, sigma: float | None = None, read: float = SHOT_READ, gain: float = SHOT_GAIN
) -> fit.NoiseModel:
    """The noise model ``--noise`` names, with its parameters."""
    from jaxrefl import fit

    if noise == "shot":
        return fit.ShotNoise(read=read, gain=gain)
    return fit.GaussianNoise(sigma=sigma)


def loss_from_flag(loss: str | None) -> fit.Loss | None:
    """The loss ``--loss`` names; None stays None (the library's default)."""
    from jaxrefl import fit

    kinds: dict[str, type[fit.Loss]] = {"l2": fit.L2, "huber": fit.Huber, "cauchy": fit.Cauchy}
    return None if loss is None else kinds[loss]()


def fit_config(
    backend: str = "lean",
    dtype: str = "float32",
    noise: str = "gaussian",
    loss: str | None = None,
    max_iters: int | None = None,
    sigma: float | None = None,
    read: float = SHOT_READ,
    gain: float = SHOT_GAIN,
) -> fit.FitConfig:
    """A :class:`~jaxrefl.fit.FitConfig` from the flags (module docstring)."""
    import numpy as np

    from jaxrefl import fit

    return fit.FitConfig(
        solver=solver_from_flags(backend, max_iters),
        noise=noise_from_flags(noise, sigma, read, gain),
        loss=loss_from_flag(loss),
        dtype=np.dtype(dtype),
    )
