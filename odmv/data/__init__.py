"""Reading datasets: samples, splits, the decoded cache and the LightningDataModule."""

from odmv.data.datamodule import FPPDataModule
from odmv.data.dataset import DataError, FringeDataset, SampleSpec, load_scene, split_scenes
from odmv.data.normalize import Normalization

__all__ = [
    "DataError",
    "FPPDataModule",
    "FringeDataset",
    "Normalization",
    "SampleSpec",
    "load_scene",
    "split_scenes",
]
