"""What a surface does to light: BRDF models, Fresnel terms, microfacet parts.

Every model follows the contract of :class:`BRDF` (see ``jaxrefl/brdf/_base.py``):
``m.eval(params, wi, wo)`` is f_r in 1/sr, without the cosine factor.
"""

from ._base import BRDF as BRDF
from ._base import Param as Param
from ._base import Params as Params
from ._base import check_directions as check_directions
from ._base import set_validation as set_validation
from ._convert import DIELECTRIC_F0_DEFAULT as DIELECTRIC_F0_DEFAULT
from ._convert import alpha_to_phong_exponent as alpha_to_phong_exponent
from ._convert import alpha_to_roughness as alpha_to_roughness
from ._convert import metallic_to_specular as metallic_to_specular
from ._convert import phong_exponent_to_alpha as phong_exponent_to_alpha
from ._convert import roughness_to_alpha as roughness_to_alpha
from ._convert import specular_to_metallic as specular_to_metallic
from ._cook_torrance import CookTorrance as CookTorrance
from ._diagnostics import directional_albedo as directional_albedo
from ._diagnostics import furnace_test as furnace_test
from ._diagnostics import hemisphere_grid as hemisphere_grid
from ._diagnostics import reciprocity_error as reciprocity_error
from ._dichromatic import Dichromatic as Dichromatic
from ._frame import cos_theta as cos_theta
from ._frame import half_vector as half_vector
from ._frame import reflect as reflect
from ._frame import safe_normalize as safe_normalize
from ._frame import spherical_direction as spherical_direction
from ._fresnel import ConductorFresnel as ConductorFresnel
from ._fresnel import DielectricFresnel as DielectricFresnel
from ._fresnel import FresnelPart as FresnelPart
from ._fresnel import NoFresnel as NoFresnel
from ._fresnel import SchlickFresnel as SchlickFresnel
from ._fresnel import f0_from_eta as f0_from_eta
from ._fresnel import fresnel_conductor as fresnel_conductor
from ._fresnel import fresnel_dielectric as fresnel_dielectric
from ._fresnel import fresnel_dielectric_polarized as fresnel_dielectric_polarized
from ._fresnel import fresnel_schlick as fresnel_schlick
from ._lafortune import Lafortune as Lafortune
from ._lambert import Lambert as Lambert
from ._lambert import OrenNayar as OrenNayar
from ._merl import MERL as MERL
from ._merl import MERL_SCALE as MERL_SCALE
from ._merl import MERL_SHAPE as MERL_SHAPE
from ._microfacet import ALPHA_MIN as ALPHA_MIN
from ._microfacet import GGX as GGX
from ._microfacet import Beckmann as Beckmann
from ._microfacet import Distribution as Distribution
from ._microfacet import Shadowing as Shadowing
from ._microfacet import SmithHeightCorrelated as SmithHeightCorrelated
from ._microfacet import SmithSeparable as SmithSeparable
from ._microfacet import VGroove as VGroove
from ._phong import BlinnPhong as BlinnPhong
from ._phong import Phong as Phong
from ._registry import available as available
from ._registry import get as get
from ._rusinkiewicz import from_half_diff as from_half_diff
from ._rusinkiewicz import to_half_diff as to_half_diff
from ._sum import Sum as Sum
from ._tilt import NormalTilt as NormalTilt
from ._tilt import tilt_frame as tilt_frame
from ._tilt import tilt_normal as tilt_normal
from ._ward import Ward as Ward
from ._zoo import ZooEntry as ZooEntry
from ._zoo import model_zoo as model_zoo
from ._zoo import random_directions as random_directions
from ._zoo import random_params as random_params

__all__ = [
    "ALPHA_MIN",
    "BRDF",
    "GGX",
    "MERL",
    "Beckmann",
    "BlinnPhong",
    "ConductorFresnel",
    "CookTorrance",
    "Dichromatic",
    "DielectricFresnel",
    "Distribution",
    "FresnelPart",
    "Lafortune",
    "Lambert",
    "NoFresnel",
    "NormalTilt",
    "OrenNayar",
    "Param",
    "Params",
    "Phong",
    "SchlickFresnel",
    "Shadowing",
    "SmithHeightCorrelated",
    "SmithSeparable",
    "Sum",
    "VGroove",
    "Ward",
    "alpha_to_phong_exponent",
    "alpha_to_roughness",
    "available",
    "cos_theta",
    "directional_albedo",
    "f0_from_eta",
    "fresnel_conductor",
    "fresnel_dielectric",
    "fresnel_dielectric_polarized",
    "fresnel_schlick",
    "from_half_diff",
    "furnace_test",
    "get",
    "half_vector",
    "metallic_to_specular",
    "phong_exponent_to_alpha",
    "reciprocity_error",
    "reflect",
    "roughness_to_alpha",
    "set_validation",
    "specular_to_metallic",
    "tilt_frame",
    "tilt_normal",
    "to_half_diff",
]
