import shutil

import pytest
from helpers import compose_config, tiny_overrides

from odmv.sim.writer import SimSettings, simulate
from odmv.training.run import train


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """Ten 64 px scenes with full sequences, rendered once per test session."""
    out = tmp_path_factory.mktemp("tiny") / "tiny"
    simulate(
        SimSettings(out=out, scenes=10, height_px=64, width_px=64, seed=1),
        workers=1,
        progress=False,
    )
    return out


@pytest.fixture
def dataset_copy(tiny_dataset, tmp_path):
    """A private copy that a test may damage."""
    return shutil.copytree(tiny_dataset, tmp_path / "copy")


@pytest.fixture(scope="session")
def trained(tiny_dataset, tmp_path_factory):
    """A tiny ODMV-Net trained for one epoch: (run folder, test metrics)."""
    out = tmp_path_factory.mktemp("run")
    metrics = train(compose_config("train", tiny_overrides(tiny_dataset, out)))
    return out, metrics
