"""Files in and out: measured BRDF data (Cornell ASTM E1392, CURET, MERL binary).

Every reader returns data in the convention of :mod:`jaxrefl.brdf` (local frame, z = normal,
directions away from the surface, f_r in 1/sr without the cosine) and raises
:class:`MeasuredDataError` (a ``ValueError``) naming the file and the problem.
"""

from ._cornell import read_cornell as read_cornell
from ._curet import read_curet as read_curet
from ._curet import read_curet_geometry as read_curet_geometry
from ._measured import MeasuredBRDF as MeasuredBRDF
from ._measured import MeasuredDataError as MeasuredDataError
from ._merl import merl_to_measured as merl_to_measured
from ._merl import read_merl as read_merl
from ._merl import read_merl_table as read_merl_table
from ._merl import write_merl as write_merl
