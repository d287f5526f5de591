import json

import numpy as np
import pytest

from odmv.io.exr import write_exr
from odmv.io.manifest import (
    DEPTH_FILE,
    LIT_FILE,
    PROJ_COORD_FILE,
    SCENE_SPEC_FILE,
    FringeSpec,
    Manifest,
    load_manifest,
)
from odmv.io.validation import validate
from odmv.rig import Rig
from odmv.validate import main

VIEWS = ("right", "down", "left", "up")


def _hand_made_dataset(root, n_scenes=2, size=16, images="full"):
    """A tiny dataset written by hand: flat plane, every projector lights the left half."""
    # the uniform image only where the full sequences are stored, as the contract says
    fringe = FringeSpec(periods_px=(1920.0, 30.0), steps=3, uniform=images == "full")
    m = Manifest(
        root,
        size,
        size,
        VIEWS,
        fringe,
        Rig(),
        images=images,
        scenes=[{"id": f"s{i}", "split": "train"} for i in range(n_scenes)],
    )
    lit = np.zeros((size, size), np.float32)
    lit[:, : size // 2] = 1
    coord = np.where(lit > 0, np.tile(np.arange(size, dtype=np.float32), (size, 1)), np.nan)
    for s in m.scenes:
        d = m.scene_dir(s["id"])
        for f in m.fringe_files(s["id"]):
            write_exr(f, {"Y": np.random.rand(size, size).astype(np.float32)})
        write_exr(d / DEPTH_FILE, {"Z": np.full((size, size), 150.0, np.float32)})
        write_exr(d / LIT_FILE, {v: lit.astype(np.float16) for v in VIEWS})
        write_exr(d / PROJ_COORD_FILE, {v: coord.astype(np.float32) for v in VIEWS})
        (d / SCENE_SPEC_FILE).write_text(json.dumps({"family": "plane"}))
    m.write()
    return m


@pytest.fixture
def dataset(tmp_path):
    return _hand_made_dataset(tmp_path / "ds")


def test_valid_dataset_passes(dataset, capsys):
    report = validate(dataset.root)
    assert report.ok, report.problems
    assert (report.scenes, report.views, report.images) == (2, 4, 2 * 4 * 7)
    assert main([str(dataset.root)]) == 0
    assert (
        capsys.readouterr().out.strip()
        == f"{dataset.root}: ok, 2 scenes, 4 views, 56 fringe images"
    )


def test_training_mode_expects_one_image_per_view(tmp_path):
    m = _hand_made_dataset(tmp_path / "t", images="training")
    assert [p.name for p in m.fringe_files("s0")] == [f"{v}_f1_s00.exr" for v in VIEWS]
    assert validate(m.root).ok


def test_missing_image_is_named(dataset, capsys):
    victim = dataset.fringe_files("s1")[5]
    victim.unlink()
    assert main([str(dataset.root)]) == 1
    out = capsys.readouterr().out.strip().splitlines()
    assert out == [f"{victim}: no such file"]


def test_corrupt_image_is_named(dataset):
    victim = dataset.fringe_files("s0")[0]
    victim.write_bytes(victim.read_bytes()[:200])
    problems = validate(dataset.root).problems
    assert len(problems) == 1 and problems[0].startswith(str(victim))


def test_nan_depth_is_named(dataset):
    depth = np.full((16, 16), 150.0, np.float32)
    depth[3, 3] = np.nan
    write_exr(dataset.scene_dir("s0") / DEPTH_FILE, {"Z": depth})
    problems = validate(dataset.root).problems
    assert len(problems) == 1 and "depth must be finite" in problems[0]
    assert validate(dataset.root, deep=False).ok  # header-only mode does not decode pixels


def test_wrong_shape_is_named(dataset):
    victim = dataset.scene_dir("s1") / DEPTH_FILE
    write_exr(victim, {"Z": np.full((8, 16), 150.0, np.float32)})
    problems = validate(dataset.root).problems
    assert problems == [
        f"{victim}: channel shape(s) {{'Z': (8, 16)}} differ from the manifest's (16, 16)"
    ]


def test_wrong_version_fails(dataset, capsys):
    path = dataset.root / "manifest.json"
    d = json.loads(path.read_text())
    d["version"] = 99
    path.write_text(json.dumps(d))
    assert main([str(dataset.root)]) == 1
    out = capsys.readouterr().out.strip()
    assert out == f"{path}: version 99 is not supported (this odmv reads 1)"


def test_manifest_round_trip(dataset):
    again = load_manifest(dataset.root)
    assert again.views == VIEWS and again.fringe == dataset.fringe and again.rig == dataset.rig
    assert [s["id"] for s in again.scenes] == ["s0", "s1"]
    assert again.fringe.highest == 1 and again.fringe.images_per_view == 7


def test_missing_manifest(tmp_path):
    problems = validate(tmp_path).problems
    assert len(problems) == 1 and "no manifest" in problems[0]


def test_footprint_is_checked_when_present(tiny_dataset, tmp_path):
    import shutil

    from odmv.io.exr import read_exr
    from odmv.io.manifest import FOOTPRINT_FILE

    root = shutil.copytree(tiny_dataset, tmp_path / "copy")
    assert validate(root).ok
    path = root / "scenes" / "000000" / FOOTPRINT_FILE
    foot = read_exr(path, list(VIEWS))
    foot["up"] = np.zeros_like(foot["up"])  # up lights pixels outside its footprint now
    write_exr(path, foot)
    problems = validate(root).problems
    assert problems == [f"{path}: channel 'up' misses pixels that up lights"]
