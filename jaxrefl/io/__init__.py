"""Files in and out: measured BRDF data (Cornell ASTM E1392, CURET, MERL binary), OpenEXR
images and maps, and photographed captures of planar samples; atomic writes
(:func:`atomic_path`, :func:`atomic_write`, :func:`write_text_atomic`,
:func:`save_npz_atomic`) for every file a resumable job or a result folder holds.

Every reader returns data in the convention of :mod:`jaxrefl.brdf` (local frame, z = normal,
directions away from the surface, f_r in 1/sr without the cosine) and raises
:class:`MeasuredDataError` (a ``ValueError``) naming the file and the problem.
"""

from ._atomic import atomic_path as atomic_path
from ._atomic import atomic_write as atomic_write
from ._atomic import write_text_atomic as write_text_atomic
from ._capture import OBS_STATUS as OBS_STATUS
from ._capture import Capture as Capture
from ._capture import CaptureError as CaptureError
from ._capture import ObsStatus as ObsStatus
from ._capture_checks import CaptureWarning as CaptureWarning
from ._capture_layouts import load_capture as load_capture
from ._capture_save import save_generic_capture as save_generic_capture
from ._channels import corr_name as corr_name
from ._channels import exr_channel as exr_channel
from ._channels import exr_channels as exr_channels
from ._channels import map_key as map_key
from ._channels import map_name as map_name
from ._cornell import read_cornell as read_cornell
from ._curet import read_curet as read_curet
from ._curet import read_curet_geometry as read_curet_geometry
from ._exr import ExrFormatError as ExrFormatError
from ._exr import ExrImage as ExrImage
from ._exr import read_exr as read_exr
from ._exr import write_exr as write_exr
from ._exr import write_exr_rgb as write_exr_rgb
from ._measured import MeasuredBRDF as MeasuredBRDF
from ._measured import MeasuredDataError as MeasuredDataError
from ._merl import merl_to_measured as merl_to_measured
from ._merl import read_merl as read_merl
from ._merl import read_merl_table as read_merl_table
from ._merl import write_merl as write_merl
from ._npz import save_npz_atomic as save_npz_atomic
from ._photos import PNGError as PNGError
from ._photos import read_png as read_png
from ._photos import write_png as write_png

__all__ = [
    "OBS_STATUS",
    "Capture",
    "CaptureError",
    "CaptureWarning",
    "ExrFormatError",
    "ExrImage",
    "MeasuredBRDF",
    "MeasuredDataError",
    "ObsStatus",
    "PNGError",
    "corr_name",
    "exr_channel",
    "load_capture",
    "map_key",
    "map_name",
    "read_cornell",
    "read_curet",
    "read_curet_geometry",
    "read_exr",
    "read_merl",
    "read_png",
    "save_generic_capture",
    "write_exr",
    "write_exr_rgb",
    "write_merl",
    "write_png",
]
