"""Frame sources (folders, files, cameras, synthetic scenarios) and results files.

Everything here sits at the edge of the package: it reads and writes data and
holds no numerics. See :func:`open_source` for the one entry point.
"""

from cpf_jax.io.base import FrameSource, LiveSource, Recording
from cpf_jax.io.cameras import KinectV2Source, RealSenseSource
from cpf_jax.io.files import NpzSource, VideoSource
from cpf_jax.io.folders import (
    ImageFolderSource,
    detect_folder_kind,
    open_folder,
    open_otb,
    open_princeton,
    open_rgbd_folder,
    open_tum,
)
from cpf_jax.io.groundtruth import load_groundtruth, load_occlusion
from cpf_jax.io.images import (
    depth_millimetres,
    princeton_depth,
    read_colour,
    read_depth,
    tum_depth,
)
from cpf_jax.io.mot import MotWriter, read_mot
from cpf_jax.io.results import ResultsWriter, read_results
from cpf_jax.io.sources import open_source
from cpf_jax.io.synthetic import SyntheticSource, open_synthetic

__all__ = [
    "MotWriter",
    "read_mot",
    "FrameSource",
    "LiveSource",
    "Recording",
    "ImageFolderSource",
    "NpzSource",
    "VideoSource",
    "SyntheticSource",
    "RealSenseSource",
    "KinectV2Source",
    "open_source",
    "open_folder",
    "open_otb",
    "open_rgbd_folder",
    "open_princeton",
    "open_tum",
    "open_synthetic",
    "detect_folder_kind",
    "load_groundtruth",
    "load_occlusion",
    "read_colour",
    "read_depth",
    "depth_millimetres",
    "princeton_depth",
    "tum_depth",
    "ResultsWriter",
    "read_results",
]
