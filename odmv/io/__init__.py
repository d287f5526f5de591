"""File formats and files: EXR images, the dataset manifest, camera images, calibration files,
point clouds, the run folder's names, and writing whole or not at all (atomic, guard)."""

from odmv.io.exr import ExrError, exr_channels, read_channel, read_exr, write_exr
from odmv.io.manifest import Manifest, ManifestError, load_manifest

__all__ = [
    "ExrError",
    "Manifest",
    "ManifestError",
    "exr_channels",
    "load_manifest",
    "read_channel",
    "read_exr",
    "write_exr",
]
