"""Command-line flags to the fit's option objects: the one place strings pick objects.

``--backend`` names a solver (``lean``: :class:`~jaxrefl.fit.LMOptions`, ``optimistix``:
:class:`~jaxrefl.fit.OptimistixLM`, ``jaxopt``: :class:`~jaxrefl.fit.JaxoptLM`) and
``--max-iters`` its iteration budget (default: the solver's own); ``--noise`` names a noise
model (``gaussian``: :class:`~jaxrefl.fit.GaussianNoise`, sigma unknown unless given;
``shot``: :class:`~jaxrefl.fit.ShotNoise`, read and gain 0.002 each unless given, linear
radiance units); ``--loss`` a robust loss (``l2``, ``huber``, ``cauchy``; none
given: the library's default); ``--dtype`` the computation dtype (``float32``,
``float64``). ``--auto-candidates``, ``--auto-pixels`` and ``--auto-seed`` (``jaxrefl fit``
and ``jaxrefl sample CAPTURE``) set the model choice's :class:`~jaxrefl.svbrdf.AutoOptions`;
a flag not given keeps AutoOptions' own default, which is read from the class when the
command runs rather than restated here (building the parser imports no JAX).
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import TYPE_CHECKING, Any

from jaxrefl._errors import JaxreflError
from jaxrefl._names import CAPTURE_MODELS, NOISE_LEVELS, canonical

from ._main import non_negative_int, positive_int

if TYPE_CHECKING:
    from jaxrefl import fit, svbrdf

__all__ = [
    "BACKENDS",
    "DTYPES",
    "LOSSES",
    "NOISES",
    "OPTIONAL_BACKENDS",
    "SHOT_GAIN",
    "SHOT_READ",
    "add_auto_arguments",
    "auto_options",
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


def _model_names(text: str) -> tuple[str, ...]:
    """``--auto-candidates``' names, canonical (checked against the capture models by
    :func:`auto_options`, whose error lists the valid names)."""
    names = tuple(canonical(t.strip()) for t in text.split(","))
    if not all(names) or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(
            f"takes distinct capture model names separated by commas (e.g. lambert,ggx), "
            f"not {text!r}"
        )
    return names


def add_auto_arguments(p: argparse.ArgumentParser) -> None:
    """The model choice's flags (module docstring); None: AutoOptions' own default."""
    p.add_argument(
        "--auto-candidates",
        type=_model_names,
        default=None,
        metavar="A,B,...",
        help="--model auto: the models scored, simplest first (ties go to the first); "
        "default: jaxrefl.svbrdf.AUTO_CANDIDATES",
    )
    p.add_argument(
        "--auto-pixels",
        type=positive_int,
        default=None,
        metavar="N",
        help="selection rows (pixels x leave-one-out folds) of --model auto's choice and of "
        "a named model's check of an estimated light; default: "
        "jaxrefl.svbrdf.AutoOptions().max_pixels",
    )
    p.add_argument(
        "--auto-seed",
        type=non_negative_int,
        default=None,
        metavar="N",
        help="seed of those selection pixels; default: jaxrefl.svbrdf.AutoOptions().seed",
    )


def auto_options(
    candidates: tuple[str, ...] | None = None,
    max_pixels: int | None = None,
    seed: int | None = None,
) -> svbrdf.AutoOptions:
    """The :class:`~jaxrefl.svbrdf.AutoOptions` of the flags given (None: its default); a
    candidate that is not a capture model is a :class:`JaxreflError` naming the flag and
    the valid names."""
    from jaxrefl import svbrdf

    unknown = [m for m in candidates or () if m not in CAPTURE_MODELS]
    if unknown:
        raise JaxreflError(
            f"--auto-candidates: unknown model {', '.join(map(repr, unknown))}; choose from "
            f"{', '.join(CAPTURE_MODELS)} (jaxrefl models NAME describes one)"
        )
    given: dict[str, Any] = {"candidates": candidates, "max_pixels": max_pixels, "seed": seed}
    return svbrdf.AutoOptions(**{k: v for k, v in given.items() if v is not None})


def add_noise_level_argument(p: argparse.ArgumentParser) -> None:
    """``--noise-level auto|flat`` (``FitJob.noise_level``)."""
    p.add_argument(
        "--noise-level",
        default=NOISE_LEVELS[0],
        choices=NOISE_LEVELS,
        help="auto (default): a per-pixel model's noise grows with the signal as the "
        "capture's residuals say, where they support it (report.json noise_level); flat: "
        "one noise level per pixel",
    )
