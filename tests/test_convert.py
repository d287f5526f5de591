"""Importers: small files in each public format -> the dataset contract -> the validator
accepts it -> the data module trains on it (invalid pixels carried as NaN depth)."""

import json
import math
import re

import numpy as np
import pytest
import scipy.io
from helpers import compose_config, tiny_overrides
from PIL import Image as PILImage

from odmv.classical.sequences import PspOptions
from odmv.importers.convert import convert
from odmv.importers.formats import FORMATS, ConvertError
from odmv.io.calibration import calibration_of
from odmv.io.exr import read_channel
from odmv.io.manifest import HEIGHT_QUANTITY, load_manifest
from odmv.io.validation import validate
from odmv.training.run import train

RNG = np.random.default_rng(0)


def _fringe(h, w):
    x = np.arange(w)[None, :] * np.ones((h, 1))
    return 0.5 + 0.4 * np.cos(2 * np.pi * x / 8 + RNG.uniform(0, 6))


def _depth(h, w, base, invalid):
    d = base + RNG.uniform(0, 20, (h, w))
    d[:, :8] = invalid  # a background band without ground truth (half survives a crop)
    return d


def _nguyen(src, h=40, w=72, n_train=10):  # 40 x 72: cropped to 32 x 64
    for part, n in (("train", n_train), ("test", 2)):
        x = np.stack([_fringe(h, w) * 255 for _ in range(n)])[..., None].astype(np.float32)
        z = np.stack([_depth(h, w, 900, 0.0) for _ in range(n)])[..., None].astype(np.float32)
        np.save(src / f"X_{part}_fringe.npy", x)
        np.save(src / f"Z_{part}.npy", z)
    return (32, 64)


def _uhrnet(src, h=32, w=48):
    np.save(src / "f1_80.npy", np.stack([_fringe(h, w) for _ in range(10)]).astype(np.float32))
    np.save(src / "Z.npy", np.stack([_depth(h, w, -5, -150.0) for _ in range(10)]))
    return (32, 48)


def _fppmlbench(src, h=32, w=32):
    (src / "fringe").mkdir()
    (src / "depth").mkdir()
    for i in range(10):
        q = np.round(_fringe(h, w) * 255).astype(np.uint8)
        PILImage.fromarray(q).save(src / "fringe" / f"obj_{i:03d}.png")
        scipy.io.savemat(src / "depth" / f"obj_{i:03d}.mat", {"depth": _depth(h, w, 300, 0.0)})
    return (32, 32)


def _folder(src, h=32, w=32):
    for i in range(10):
        scene = src / f"part{i:02d}"
        scene.mkdir()
        for v in ("right", "up"):
            q = np.round(_fringe(h, w) * 65535).astype(np.uint16)
            PILImage.fromarray(q).save(scene / f"{v}.png")
        np.save(scene / "depth.npy", _depth(h, w, 150, np.nan).astype(np.float32))
    return (32, 32)


WRITERS = {"nguyen2020": _nguyen, "uhrnet": _uhrnet, "fppmlbench": _fppmlbench, "folder": _folder}


FIRST_NAMES = {
    "nguyen2020": "X_train_fringe.npy[0]",
    "uhrnet": "f1_80.npy[0]",
    "fppmlbench": "fringe/obj_000.png",
    "folder": "part00",
}
SAID = {  # how each source's intensities are stored, as convert says it
    "nguyen2020": "divided by 255 (floats above 1.5)",
    "uhrnet": "as stored (floats in [0, 1])",
    "fppmlbench": "divided by 255",
    "folder": "divided by 65535",  # 16-bit PNG files
}


def test_every_import_format_is_written_by_a_test():
    """A format is one entry of FORMATS; the tests here make a source of each (those read with
    a rig's calibration: the sequences' own test below)."""
    assert set(WRITERS) == {k for k, e in FORMATS.items() if not e.rig}
    assert [k for k, e in FORMATS.items() if e.rig] == ["sequences"]
    assert all(e.quantity in ("depth", "height") and e.reads for e in FORMATS.values())


@pytest.mark.parametrize("fmt", list(WRITERS))
def test_import_validates_and_trains(fmt, tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    size = WRITERS[fmt](src)
    out = tmp_path / "dataset"
    m = convert(fmt, src, out)
    assert f"intensity: {src}: {SAID[fmt]}\n" in capsys.readouterr().out
    first = json.loads((out / "scenes" / "000000" / "scene.json").read_text())
    assert first["source_name"] == FIRST_NAMES[fmt]  # the source's own name of the sample
    assert (m.height_px, m.width_px) == size
    report = validate(out)
    assert report.ok, report.problems
    meta = json.loads((out / "manifest.json").read_text())
    assert meta["source"]["format"] == fmt and meta["rig_known"] is False
    assert meta["invalid_depth"] == "nan" and meta["depth_range_mm"][0] < meta["depth_range_mm"][1]
    splits = [s["split"] for s in meta["scenes"]]
    assert {"train", "val", "test"} <= set(splits)
    depth = read_channel(out / "scenes" / "000000" / "depth.exr", "Z")
    assert np.isnan(depth).any() and np.isfinite(depth).any()  # the invalid band carried over
    if FORMATS[fmt].quantity == "height":  # a height map, so trained and scored as height
        assert meta["quantity"] == HEIGHT_QUANTITY and meta["units"]["depth"] == HEIGHT_QUANTITY
    metrics = _train_on(out, tmp_path, m.views, size)
    assert math.isfinite(metrics["test/mae_mm"]) and math.isfinite(metrics["test/loss"])


def _train_on(dataset, tmp_path, views, size, *extra):
    """One tiny UNet epoch on ``dataset`` at its own ``size``; returns the test metrics."""
    overrides = [
        o
        for o in tiny_overrides(dataset, tmp_path)
        if not o.startswith(("model.net.", "data.resolution"))
    ]
    cfg = compose_config(
        "train",
        [
            *overrides,
            "model=unet",
            "widths.unet=4",
            f"views={list(views)}".replace("'", ""),
            f"data.resolution=[{size[0]},{size[1]}]",
            *extra,
        ],
    )
    return train(cfg)


def test_a_uhrnet_sample_becomes_height_in_0_1_without_its_fill(tmp_path, capsys):
    """The sample the UHRNet repository ships: fringes in [-1, 1], height with -105 fill."""
    src = tmp_path / "src"
    src.mkdir()
    fringe = (2 * _fringe(32, 48) - 1).astype(np.float32)
    height = RNG.uniform(60, 180, (32, 48)).astype(np.float32)
    height[:, :10] = -105.0  # no data
    height[:, 10:20] = -97.0 + RNG.normal(0, 0.5, (32, 10))  # the measured background
    np.save(src / "fringe_pattern.npy", fringe)
    np.save(src / "height_map.npy", height)
    m = convert("uhrnet", src, tmp_path / "ds")
    assert "stored in [-1, 1], mapped by (x + 1) / 2" in capsys.readouterr().out
    image = read_channel(tmp_path / "ds" / "scenes" / "000000" / "fringe" / "right_f0_s00.exr", "Y")
    np.testing.assert_allclose(image, (fringe + 1) / 2, atol=1e-6)
    meta = json.loads((tmp_path / "ds" / "manifest.json").read_text())
    assert meta["quantity"] == HEIGHT_QUANTITY and meta["rig"] is None and m.rig is None
    lo, hi = meta["depth_range_mm"]
    assert -100 < lo < -95 and 170 < hi <= 180  # over the valid pixels only
    depth = read_channel(tmp_path / "ds" / "scenes" / "000000" / "depth.exr", "Z")
    assert np.isnan(depth[:, :10]).all() and np.isfinite(depth[:, 10:]).all()
    assert validate(tmp_path / "ds").ok
    convert("uhrnet", src, tmp_path / "raw", intensity="as_is")
    (problem,) = validate(tmp_path / "raw").problems
    assert re.fullmatch(
        r".*right_f0_s00.exr: fringe intensities in \[-0.79, 0.79\] are negative; .*intensity=auto",
        problem,
    )


def test_a_source_without_val_needs_and_takes_val_from_train(tmp_path, capsys):
    """Labelled train and test only: the error names the fix, and the fix trains."""
    src = tmp_path / "src"
    src.mkdir()
    size = _nguyen(src, n_train=5)  # too few for the format's own val share
    m = convert("nguyen2020", src, tmp_path / "ds")
    assert {s["split"] for s in m.scenes} == {"train", "test"}
    with pytest.raises(ValueError, match=r"the val split .* is empty; set data.val_from_train="):
        _train_on(tmp_path / "ds", tmp_path / "a", m.views, size)
    metrics = _train_on(tmp_path / "ds", tmp_path / "b", m.views, size, "data.val_from_train=0.2")
    assert "1 of the 5 training scenes are the val split" in capsys.readouterr().out
    assert math.isfinite(metrics["test/mae_mm"])


def test_sequences_of_a_rig_become_a_dataset_with_the_classical_ground_truth(
    tiny_dataset, tmp_path
):
    """The twin's sequences as 16-bit PNG with its calibration file, converted back: the
    decoded depth is the twin's where kept, the calibration travels with the dataset (the
    reference-phase input works), and a net trains on it."""
    twin = load_manifest(tiny_dataset)
    src = tmp_path / "captures"
    ids = [s["id"] for s in twin.scenes[:5]]
    for sid in ids:
        for path in (twin.scene_dir(sid) / "fringe").glob("*_f*_s*.exr"):
            level = np.round(np.clip(read_channel(path, "Y"), 0, 1) * 65535).astype(np.uint16)
            (src / sid).mkdir(parents=True, exist_ok=True)
            PILImage.fromarray(level).save(src / sid / f"{path.stem}.png")
    calibration = tmp_path / "rig.json"
    calibration.write_text(json.dumps(calibration_of(twin.rig, 64, 64)))
    m = convert("sequences", src, tmp_path / "ds", calibration=calibration, psp=PspOptions())
    assert m.views == twin.views and m.fringe.steps == 12
    meta = json.loads((tmp_path / "ds" / "manifest.json").read_text())
    assert meta["source"]["decoder"]["periods"] is None  # the twin's: 1, 8 and 64 periods
    assert meta["rig"]["calibration"]["reference_plane_mm"] == 150.0
    assert validate(tmp_path / "ds").ok
    errors, kept = [], []
    for k, sid in enumerate(ids):
        truth = read_channel(twin.scene_dir(sid) / "depth.exr", "Z")
        depth = read_channel(m.scene_dir(f"{k:06d}") / "depth.exr", "Z")
        ok = np.isfinite(depth)
        errors.append(np.abs(depth - truth)[ok])
        kept.append(ok.mean())
    assert np.concatenate(errors).mean() < 0.05 and min(kept) > 0.5
    metrics = _train_on(tmp_path / "ds", tmp_path / "run", m.views, (32, 32), "reference=true")
    assert math.isfinite(metrics["test/mae_mm"])


def test_reference_input_is_refused_for_an_import(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    _uhrnet(src)
    convert("uhrnet", src, tmp_path / "ds")
    cfg = compose_config(
        "train",
        [
            *(o for o in tiny_overrides(tmp_path / "ds", tmp_path) if not o.startswith("model.")),
            "model=unet",
            "views=1",
            "reference=true",
        ],
    )
    with pytest.raises(ValueError, match="has no rig calibration"):
        train(cfg)


def test_bad_sources_are_named_and_leave_nothing(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    with pytest.raises(ConvertError, match=r"X_train_fringe.npy: no such file"):
        convert("nguyen2020", src, tmp_path / "out")
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))
    np.save(src / "f1_80.npy", np.zeros((3, 32, 32), np.float32))
    np.save(src / "Z.npy", np.zeros((3, 32, 16), np.float32))
    with pytest.raises(ConvertError, match=r"Z.npy: shape \(3, 32, 16\) differs"):
        convert("uhrnet", src, tmp_path / "out")
    with pytest.raises(ConvertError, match="format: 'kinect' unknown"):
        convert("kinect", src, tmp_path / "out")
