"""File formats shared by the simulator and the data module: EXR images and the manifest."""

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
