"""From parameters to pixels: lights, cameras, camera response and image formation.

``render(model, params, lights, camera, points=...)`` gives one radiance image per light,
``(K, *P, C)``; see :mod:`jaxrefl.scene._render` for the formula and the order of the steps.
Lights give incident samples (direction towards the light, normal-incidence irradiance);
cameras give view directions and cos^4 falloff; responses encode radiance to pixel values.
"""

from ._camera import Camera as Camera
from ._camera import GammaResponse as GammaResponse
from ._camera import LinearResponse as LinearResponse
from ._camera import OrthographicCamera as OrthographicCamera
from ._camera import PinholeCamera as PinholeCamera
from ._camera import Response as Response
from ._camera import SRGBResponse as SRGBResponse
from ._camera import TabulatedResponse as TabulatedResponse
from ._camera import cos4_falloff as cos4_falloff
from ._geometry import orthonormal_basis as orthonormal_basis
from ._geometry import planar_points as planar_points
from ._geometry import shading_frame as shading_frame
from ._geometry import to_local as to_local
from ._geometry import to_world as to_world
from ._lights import AreaLight as AreaLight
from ._lights import DirectionalLight as DirectionalLight
from ._lights import EnvironmentMap as EnvironmentMap
from ._lights import Light as Light
from ._lights import PointLight as PointLight
from ._render import render as render
from ._render import render_planar_sample as render_planar_sample
from ._sh import SH_CONSTANTS as SH_CONSTANTS
from ._sh import sh_basis as sh_basis
from ._sh import sh_irradiance as sh_irradiance
from ._sh import sh_lambert as sh_lambert
from ._sh import sh_project as sh_project

__all__ = [
    "SH_CONSTANTS",
    "AreaLight",
    "Camera",
    "DirectionalLight",
    "EnvironmentMap",
    "GammaResponse",
    "Light",
    "LinearResponse",
    "OrthographicCamera",
    "PinholeCamera",
    "PointLight",
    "Response",
    "SRGBResponse",
    "TabulatedResponse",
    "cos4_falloff",
    "planar_points",
    "render",
    "render_planar_sample",
    "sh_basis",
    "sh_irradiance",
    "sh_lambert",
    "sh_project",
]
