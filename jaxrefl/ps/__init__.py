"""Photometric stereo and inverse lighting: normals, albedo, lights and depth from images
of an object under distant lights.

Conventions (see ``_capture``): camera frame x right, y up, z towards the camera
(orthographic view +z); image row 0 at the top, pixel (i, j) at x = j, y = -i; lights are
unit vectors towards the light with intensities per image and channel; I = E rho n.l.

* Calibrated: :func:`woodham` (least squares), :func:`robust` (shadows and highlights
  rejected by IRLS), :func:`fit_normal_brdf` (normal + microfacet BRDF per pixel with the
  :mod:`jaxrefl.fit` engine); their settings are method objects, which
  :func:`solve_capture` and :func:`run_ps` also take: :class:`LeastSquares`,
  :class:`Robust` (``robust(..., options)``), :class:`NormalBRDF`
  (``fit_normal_brdf(..., options)``); ``METHODS[name]`` by name.
* Uncalibrated: :func:`factorize` (rank-3 SVD), :func:`gbr_matrix` / :func:`apply_gbr`
  (the bas-relief ambiguity), :func:`uncalibrated` (resolved by known normals in view).
* Lights: :func:`chrome_sphere_lights`, :func:`lambertian_sphere_lights`,
  :func:`lights_from_shading`, with uncertainties.
* Depth: :func:`frankot_chellappa`, :func:`poisson`.
* Evaluation: :func:`angular_error`, :func:`error_stats`, :func:`sphere_error`,
  :func:`fit_circle`, :func:`sphere_normals`.
* Files: :func:`load_uw`, :func:`load_diligent`, :func:`load_capture`,
  :func:`save_diligent`; :func:`run_ps` (the ``jaxrefl ps`` command).
"""

from ._brdf import BRDFFit as BRDFFit
from ._brdf import NormalBRDF as NormalBRDF
from ._brdf import NormalBRDFResidual as NormalBRDFResidual
from ._brdf import default_model as default_model
from ._brdf import fit_normal_brdf as fit_normal_brdf
from ._brdf import tilt_normal as tilt_normal
from ._capture import PSCapture as PSCapture
from ._capture import PSInputError as PSInputError
from ._capture import check_lights as check_lights
from ._eval import ErrorStats as ErrorStats
from ._eval import angular_error as angular_error
from ._eval import error_stats as error_stats
from ._eval import sphere_error as sphere_error
from ._integrate import frankot_chellappa as frankot_chellappa
from ._integrate import poisson as poisson
from ._io import load_capture as load_capture
from ._io import load_diligent as load_diligent
from ._io import load_uw as load_uw
from ._io import save_diligent as save_diligent
from ._job import run_ps as run_ps
from ._job import solve_capture as solve_capture
from ._lights import LightCalibration as LightCalibration
from ._lights import chrome_sphere_lights as chrome_sphere_lights
from ._lights import lambertian_sphere_lights as lambertian_sphere_lights
from ._lights import lights_from_shading as lights_from_shading
from ._mat import read_mat as read_mat
from ._mat import write_mat as write_mat
from ._method import PSMethod as PSMethod
from ._methods import METHODS as METHODS
from ._methods import LeastSquares as LeastSquares
from ._robust import Robust as Robust
from ._robust import robust as robust
from ._sphere import Circle as Circle
from ._sphere import fit_circle as fit_circle
from ._sphere import sphere_normals as sphere_normals
from ._synthetic import bump_surface as bump_surface
from ._synthetic import render as render
from ._synthetic import sphere_surface as sphere_surface
from ._synthetic import spiral_lights as spiral_lights
from ._uncalibrated import UncalibratedResult as UncalibratedResult
from ._uncalibrated import apply_gbr as apply_gbr
from ._uncalibrated import factorize as factorize
from ._uncalibrated import gbr_matrix as gbr_matrix
from ._uncalibrated import resolve_with_known_normals as resolve_with_known_normals
from ._uncalibrated import uncalibrated as uncalibrated
from ._woodham import PSResult as PSResult
from ._woodham import woodham as woodham

__all__ = [
    "METHODS",
    "BRDFFit",
    "Circle",
    "ErrorStats",
    "LeastSquares",
    "LightCalibration",
    "NormalBRDF",
    "PSCapture",
    "PSInputError",
    "PSMethod",
    "PSResult",
    "Robust",
    "UncalibratedResult",
    "angular_error",
    "apply_gbr",
    "bump_surface",
    "chrome_sphere_lights",
    "default_model",
    "error_stats",
    "factorize",
    "fit_circle",
    "fit_normal_brdf",
    "frankot_chellappa",
    "gbr_matrix",
    "lambertian_sphere_lights",
    "lights_from_shading",
    "load_capture",
    "load_diligent",
    "load_uw",
    "poisson",
    "read_mat",
    "render",
    "resolve_with_known_normals",
    "robust",
    "run_ps",
    "save_diligent",
    "solve_capture",
    "sphere_error",
    "sphere_normals",
    "sphere_surface",
    "spiral_lights",
    "tilt_normal",
    "uncalibrated",
    "woodham",
    "write_mat",
]
