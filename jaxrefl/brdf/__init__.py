"""What a surface does to light: BRDF models, Fresnel terms, microfacet parts.

Every model follows the contract of :class:`BRDF` (see ``jaxrefl/brdf/_base.py``):
``m.eval(params, wi, wo)`` is f_r in 1/sr, without the cosine factor.
"""

from ._base import BRDF as BRDF
from ._base import Param as Param
from ._base import Params as Params
from ._convert import (
    alpha_to_phong_exponent as alpha_to_phong_exponent,
)
from ._convert import (
    alpha_to_roughness as alpha_to_roughness,
)
from ._convert import (
    phong_exponent_to_alpha as phong_exponent_to_alpha,
)
from ._convert import (
    roughness_to_alpha as roughness_to_alpha,
)
from ._merl import MERL as MERL
from ._microfacet import (
    ALPHA_MIN as ALPHA_MIN,
    GGX as GGX,
    Beckmann as Beckmann,
    Distribution as Distribution,
    Shadowing as Shadowing,
    SmithHeightCorrelated as SmithHeightCorrelated,
    SmithSeparable as SmithSeparable,
    VGroove as VGroove,
)
from ._registry import available as available
from ._merl import MERL as MERL
from ._microfacet import (
    ALPHA_MIN as ALPHA_MIN,
    GGX as GGX,
    Beckmann as Beckmann,
    Distribution as Distribution,
    Shadowing as Shadowing,
    SmithHeightCorrelated as SmithHeightCorrelated,
    SmithSeparable as SmithSeparable,
    VGroove as VGroove,
)
from ._registry import get as get
from ._rusinkiewicz import from_half_diff as from_half_diff, to_half_diff as to_half_diff
from ._sum import Sum as Sum
from ._cook_torrance import CookTorrance as CookTorrance
from ._diagnostics import (
    directional_albedo as directional_albedo,
    furnace_test as furnace_test,
    hemisphere_grid as hemisphere_grid,
    reciprocity_error as reciprocity_error,
)
from ._dichromatic import Dichromatic as Dichromatic
from ._fresnel import (
    ConductorFresnel as ConductorFresnel,
    DielectricFresnel as DielectricFresnel,
    FresnelPart as FresnelPart,
    NoFresnel as NoFresnel,
    SchlickFresnel as SchlickFresnel,
    f0_from_eta as f0_from_eta,
    fresnel_conductor as fresnel_conductor,
    fresnel_dielectric as fresnel_dielectric,
    fresnel_dielectric_polarized as fresnel_dielectric_polarized,
    fresnel_schlick as fresnel_schlick,
)
from ._frame import (
    cos_theta as cos_theta,
    half_vector as half_vector,
    reflect as reflect,
    spherical_direction as spherical_direction,
)
from ._zoo import (
    ZooEntry as ZooEntry,
    model_zoo as model_zoo,
    random_directions as random_directions,
    random_params as random_params,
)
