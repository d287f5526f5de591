"""The classical method on fewer images per projector, down to the network's one image
(odmv.classical.reconstruct.Capture): the full capture is the classical row, and fewer images
cost accuracy or coverage, never correctness."""

import dataclasses

import numpy as np
import pytest
from helpers import compose_config

from odmv.classical.fringe import demodulate
from odmv.classical.reconstruct import CAPTURES, Capture
from odmv.data.dataset import DataError
from odmv.deploy.predict import predict
from odmv.io.exr import read_channel, write_exr
from odmv.io.manifest import FringeSpec
from odmv.sim.writer import SimSettings, simulate
from odmv.study.classical import classical_row


@pytest.fixture(scope="module")
def twin_240(tmp_path_factory):
    """Ten 64 px scenes whose network image is the 240 px fringe, as in the mini protocol."""
    out = tmp_path_factory.mktemp("twin240") / "twin"
    fringe = dataclasses.replace(FringeSpec(), train_frequency=1)
    simulate(
        SimSettings(out=out, scenes=10, height_px=64, width_px=64, seed=1, fringe=fringe),
        workers=1,
        progress=False,
    )
    return out


def test_demodulation_recovers_a_phase_offset_on_a_uniform_carrier():
    x = np.arange(96)
    ref = 2 * np.pi * np.tile(x / 9.6, (40, 1))  # a 9.6 px carrier along the columns
    image = 0.4 + 0.3 * np.cos(ref + 0.7)
    dphi, mod = demodulate(image, ref, 9.6, axis=1)
    inner = np.s_[:, 10:-10]  # away from the ends, where the filter runs out of image
    # a box of a fractional period on whole pixels leaves a ripple of 1/600 of a period
    assert np.abs(dphi[inner] - 0.7).max() < 0.01 and np.abs(mod[inner] - 0.3).max() < 3e-3


@pytest.mark.slow
def test_fewer_images_cost_accuracy_or_coverage(twin_240, tmp_path):
    full = classical_row(twin_240, tmp_path / "full", split="train")
    got = {}
    for c in CAPTURES:
        got[c] = classical_row(twin_240, tmp_path / c.name, split="train", capture=c)
        # the report tells a capture's row from the classical row by what its record says
        assert got[c]["images_per_projector"] == c.images and got[c]["capture"] == c.key
    assert "capture" not in full and "images_per_projector" not in full
    # every step of both resolved frequencies is the classical row itself
    both = got[Capture(12, 2)]
    assert both["test/mae_mm"] == pytest.approx(full["test/mae_mm"], rel=1e-6)
    assert both["test/coverage"] == pytest.approx(full["test/coverage"], rel=1e-6)
    # one frequency: the order is anchored to the plane, so tall parts can be a period off
    for steps in (3, 4, 12):
        one = got[Capture(steps)]
        assert one["test/mae_mm"] < 0.1 and one["test/coverage"] > 0.6
    ftp = got[CAPTURES[0]]
    assert ftp["test/mae_mm"] > 3 * both["test/mae_mm"] and ftp["test/coverage"] > 0.3
    assert ftp["test/mae_mm"] < 1.0  # sub-mm from one image per projector


@pytest.mark.slow
def test_predict_ftp_decodes_the_one_network_image_per_view(twin_240, tmp_path):
    scene = twin_240 / "scenes" / "000004"
    cfg = compose_config(
        "predict",
        ["method=ftp", f"input={scene}", f"out={tmp_path / 'a'}", f"paths.output_dir={tmp_path}"],
    )
    depth = read_channel(predict(cfg)[0]["depth"], "Z")
    truth = read_channel(scene / "depth.exr", "Z")
    kept = np.isfinite(depth)
    assert 0.3 < kept.mean() and np.median(np.abs(depth - truth)[kept]) < 0.3  # mm
    # the same images as a folder of <view>.exr, with the dataset naming their fringe
    folder = tmp_path / "capture"
    for v in ("right", "down", "left", "up"):
        image = read_channel(scene / "fringe" / f"{v}_f1_s00.exr", "Y")
        write_exr(folder / f"{v}.exr", {"Y": image})
    base = ["method=ftp", f"input={folder}", f"paths.output_dir={tmp_path}"]
    cfg = compose_config("predict", [*base, f"out={tmp_path / 'b'}", f"manifest={twin_240}"])
    np.testing.assert_array_equal(read_channel(predict(cfg)[0]["depth"], "Z"), depth)
    with pytest.raises(DataError, match="method=ftp needs the fringe's period"):
        predict(compose_config("predict", [*base, f"out={tmp_path / 'c'}"]))
