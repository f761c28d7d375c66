"""Pixels to best parameters: batched least squares for reflectance models.

Quick use::

    import jaxrefl
    from jaxrefl import fit

    model = jaxrefl.brdf.get("cook_torrance", distribution="ggx", diffuse="lambert")
    data = fit.pixel_data(obs, wi, wo, scale=irradiance_cos)   # (N, K, C), (N, K, 3) ...
    result = fit.fit_pixels(model, data)                       # lean batched LM
    result.params["alpha"], result.status_counts()
    cfg = fit.FitConfig(solver=fit.LMOptions(max_iters=80), noise=fit.ShotNoise(0.002, 0.002),
                        loss=fit.Huber(), dtype=jnp.float32)
    result = fit.fit_pixels(model, data, config=cfg)

Parts: :class:`ParamSpace` and the bijections (unconstrained parametrisation), :class:`PixelData`
and :func:`make_residual` (noise models, robust losses, censoring), :func:`initial_theta`
(closed-form colours on a roughness grid), :func:`lm_solve` / :func:`batched_lm` (the lean
Levenberg-Marquardt as pure init/step functions; its unrolled Cholesky and triangular solves
are the shared small linear algebra of :mod:`._linalg`), :func:`solve` (the solver objects
:class:`LMOptions`, :class:`OptimistixLM`, :class:`JaxoptLM`), :class:`FitConfig` (solver,
noise, loss and dtype of a fit, taken by every fitting entry point), per-pixel
:class:`Status` codes, and :func:`laplace` (Gauss-Newton covariance in natural units with
reliability flags, configured by :class:`LaplaceOptions`). :func:`map_sharded` spreads a
batch of pixels over this process's devices; :class:`Distributed` names the process group of
a job split over processes and hosts (JAX's distributed runtime; :mod:`._distributed` shares
out, waits for and gathers the work); a process that stops makes the others' barrier raise
:class:`ProcessGroupError`, and :func:`leave_group` ends them at once;
:class:`WorkStore` keeps a job's finished pieces in a folder the processes share, for resume.
"""

from ._backends import FitInfo as FitInfo
from ._backends import JaxoptLM as JaxoptLM
from ._backends import OptimistixLM as OptimistixLM
from ._backends import Solver as Solver
from ._backends import solve as solve
from ._distributed import Distributed as Distributed
from ._distributed import ProcessGroupError as ProcessGroupError
from ._distributed import leave_group as leave_group
from ._distributed import (
    process_barrier,  # noqa: F401
    process_gather,  # noqa: F401
    process_share,  # noqa: F401
)
from ._init import initial_theta as initial_theta
from ._laplace import LaplaceFlag as LaplaceFlag
from ._laplace import LaplaceOptions as LaplaceOptions
from ._laplace import LaplaceResult as LaplaceResult
from ._laplace import (
    flag_counts,  # noqa: F401
    same_residual,  # noqa: F401
    undefined_correlations,  # noqa: F401
)
from ._laplace import laplace as laplace
from ._linalg import (
    cho_solve_unrolled,  # noqa: F401
    cholesky_unrolled,  # noqa: F401
    solve_lower_t_unrolled,  # noqa: F401
    solve_lower_unrolled,  # noqa: F401
)
from ._lm import LMInfo as LMInfo
from ._lm import LMOptions as LMOptions
from ._lm import LMResult as LMResult
from ._lm import LMState as LMState
from ._lm import lm_init as lm_init
from ._lm import lm_solve as lm_solve
from ._lm import lm_step as lm_step
from ._lm_batched import batched_lm as batched_lm
from ._options import Option as Option
from ._options import check_number  # noqa: F401
from ._problem import FitConfig as FitConfig
from ._problem import FitResult as FitResult
from ._problem import Linearisation as Linearisation
from ._problem import SamplesOptions as SamplesOptions
from ._problem import fit_pixels as fit_pixels
from ._problem import fit_samples as fit_samples
from ._problem import sample_arrays  # noqa: F401
from ._residual import L2 as L2
from ._residual import Cauchy as Cauchy
from ._residual import GaussianNoise as GaussianNoise
from ._residual import GaussianPrior as GaussianPrior
from ._residual import Huber as Huber
from ._residual import LevelNoise as LevelNoise
from ._residual import Loss as Loss
from ._residual import NoiseModel as NoiseModel
from ._residual import PixelData as PixelData
from ._residual import Residual as Residual
from ._residual import ShotNoise as ShotNoise
from ._residual import gaussian_prior as gaussian_prior
from ._residual import make_residual as make_residual
from ._residual import pixel_data as pixel_data
from ._residual import replace_params  # noqa: F401
from ._select import keep_lower  # noqa: F401
from ._shard import device_count  # noqa: F401
from ._shard import map_sharded as map_sharded
from ._status import STATUS_MEANINGS as STATUS_MEANINGS
from ._status import Status as Status
from ._status import describe as describe
from ._status import equilibrated_condition  # noqa: F401
from ._status import has_estimate as has_estimate
from ._status import most_severe as most_severe
from ._status import severity as severity
from ._transform import Bijection as Bijection
from ._transform import Exp as Exp
from ._transform import Identity as Identity
from ._transform import Log as Log
from ._transform import ParamSpace as ParamSpace
from ._transform import ScaledSigmoid as ScaledSigmoid
from ._transform import Softplus as Softplus
from ._transform import UnitVector as UnitVector
from ._work_store import WorkStore as WorkStore
from ._work_store import (
    fingerprint_hash,  # noqa: F401
    refuse_other_work,  # noqa: F401
)

# The public names. Those imported above without ``as`` are helpers the other packages of
# jaxrefl share (each package uses another through its ``__init__`` only), not public.
__all__ = [
    "L2",
    "STATUS_MEANINGS",
    "Bijection",
    "Cauchy",
    "Distributed",
    "Exp",
    "FitConfig",
    "FitInfo",
    "FitResult",
    "GaussianNoise",
    "GaussianPrior",
    "Huber",
    "Identity",
    "JaxoptLM",
    "LMInfo",
    "LMOptions",
    "LMResult",
    "LMState",
    "LaplaceFlag",
    "LaplaceOptions",
    "LaplaceResult",
    "LevelNoise",
    "Linearisation",
    "Log",
    "Loss",
    "NoiseModel",
    "OptimistixLM",
    "Option",
    "ParamSpace",
    "PixelData",
    "ProcessGroupError",
    "Residual",
    "SamplesOptions",
    "ScaledSigmoid",
    "ShotNoise",
    "Softplus",
    "Solver",
    "Status",
    "UnitVector",
    "WorkStore",
    "batched_lm",
    "describe",
    "fit_pixels",
    "fit_samples",
    "gaussian_prior",
    "has_estimate",
    "initial_theta",
    "laplace",
    "leave_group",
    "lm_init",
    "lm_solve",
    "lm_step",
    "make_residual",
    "map_sharded",
    "most_severe",
    "pixel_data",
    "severity",
    "solve",
]
