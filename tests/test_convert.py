"""Importers: small files in each public format -> the dataset contract -> the validator
accepts it -> the data module trains on it (invalid pixels carried as NaN depth)."""

import json
import math

import numpy as np
import pytest
import scipy.io
from helpers import compose_config, tiny_overrides
from PIL import Image as PILImage

from odmv.convert import ConvertError, convert
from odmv.io.exr import read_channel
from odmv.train import train
from odmv.validate import validate

RNG = np.random.default_rng(0)


def _fringe(h, w):
    x = np.arange(w)[None, :] * np.ones((h, 1))
    return 0.5 + 0.4 * np.cos(2 * np.pi * x / 8 + RNG.uniform(0, 6))


def _depth(h, w, base, invalid):
    d = base + RNG.uniform(0, 20, (h, w))
    d[:, :8] = invalid  # a background band without ground truth (half survives a crop)
    return d


def _nguyen(src, h=40, w=72):  # 40 x 72: cropped to 32 x 64
    for part, n in (("train", 10), ("test", 2)):
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


@pytest.mark.parametrize("fmt", list(WRITERS))
def test_import_validates_and_trains(fmt, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    size = WRITERS[fmt](src)
    out = tmp_path / "dataset"
    m = convert(fmt, src, out)
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
    overrides = [
        o
        for o in tiny_overrides(out, tmp_path)
        if not o.startswith(("model.net.", "data.resolution"))
    ]
    cfg = compose_config(
        "train",
        [
            *overrides,
            "model=unet",
            "widths.unet=4",
            f"views={list(m.views)}".replace("'", ""),
            f"data.resolution=[{size[0]},{size[1]}]",
        ],
    )
    metrics = train(cfg)
    assert math.isfinite(metrics["test/mae_mm"]) and math.isfinite(metrics["test/loss"])


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
    with pytest.raises(ValueError, match="imported without a rig calibration"):
        train(cfg)


def test_bad_sources_are_named_and_leave_nothing(tmp_path):
    with pytest.raises(ConvertError, match=r"X_train_fringe.npy: no such file"):
        convert("nguyen2020", tmp_path, tmp_path / "out")
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))
    np.save(tmp_path / "f1_80.npy", np.zeros((3, 32, 32), np.float32))
    np.save(tmp_path / "Z.npy", np.zeros((3, 32, 16), np.float32))
    with pytest.raises(ConvertError, match=r"Z.npy: shape \(3, 32, 16\) differs"):
        convert("uhrnet", tmp_path, tmp_path / "out")
    with pytest.raises(ConvertError, match="format: 'kinect' unknown"):
        convert("kinect", tmp_path, tmp_path / "out")
