"""predict on the files rigs write: every image format, many scenes, explicit scaling and
resizing, valid-only point clouds, and the classical method on full sequences."""

import shutil
import subprocess
import sys

import numpy as np
import OpenEXR
import pytest
from helpers import compose_config
from PIL import Image as PILImage

from odmv.deploy.predict import predict
from odmv.io.calibration import calibration_of
from odmv.io.exr import read_channel, write_exr
from odmv.io.images import ImageError, fit_to, read_image

VIEWS = ("right", "down", "left", "up")


def _views(scene):
    return {v: read_channel(scene / "fringe" / f"{v}_f2_s00.exr", "Y") for v in VIEWS}


def _save(folder, name, image, fmt):
    """Write one view in ``fmt``; returns the intensity the file holds (after quantization)."""
    folder.mkdir(parents=True, exist_ok=True)
    a = np.clip(image, 0, 1)
    if fmt == "exr":
        write_exr(folder / f"{name}.exr", {"Y": image})
        return image
    if fmt == "npy":
        np.save(folder / f"{name}.npy", image.astype(np.float32))
        return image
    if fmt in ("png8", "bmp8"):
        q = np.round(a * 255).astype(np.uint8)
        PILImage.fromarray(q).save(folder / f"{name}.{fmt[:3]}")
        return q / 255.0
    if fmt in ("png16", "tif16"):
        q = np.round(a * 65535).astype(np.uint16)
        PILImage.fromarray(q).save(folder / f"{name}.{fmt[:3]}")
        return q / 65535.0
    if fmt == "tiff32":
        PILImage.fromarray(image.astype(np.float32)).save(folder / f"{name}.tiff")
        return image
    raise AssertionError(fmt)


def _predict(ckpt, folder, out, *extra):
    cfg = compose_config(
        "predict",
        [f"ckpt_path={ckpt}", f"input={folder}", f"out={out}", f"paths.output_dir={out}", *extra],
    )
    return predict(cfg)


@pytest.mark.parametrize("fmt", ["exr", "npy", "tiff32", "png16", "tif16", "png8", "bmp8"])
def test_each_format_reads_back_and_predicts(fmt, trained, tiny_dataset, tmp_path):
    ckpt = trained[1]["best_checkpoint"]
    images = _views(tiny_dataset / "scenes" / "000004")
    folder = tmp_path / fmt
    held = {v: _save(folder, v, img, fmt) for v, img in images.items()}
    for v in VIEWS:
        path = next(folder.glob(f"{v}.*"))
        im = read_image(path)
        np.testing.assert_allclose(im.data / im.full_scale, held[v], atol=1e-6)
    (ours,) = _predict(ckpt, folder, tmp_path / "out")
    (ref,) = _predict(ckpt, tiny_dataset / "scenes" / "000004", tmp_path / "ref")
    got, want = read_channel(ours["depth"], "Z"), read_channel(ref["depth"], "Z")
    tolerance = {"png8": 0.5, "bmp8": 0.5, "png16": 0.01, "tif16": 0.01}.get(fmt, 1e-4)
    assert np.abs(got - want).max() < tolerance  # mm


def test_scale_and_fit_are_explicit_and_printed(trained, tiny_dataset, tmp_path, capsys):
    ckpt = trained[1]["best_checkpoint"]
    images = _views(tiny_dataset / "scenes" / "000004")
    folder = tmp_path / "wide"
    folder.mkdir()
    for v, img in images.items():  # a 64 x 48 capture of 12-bit values in 16-bit PNG
        q = np.round(np.clip(img[8:56], 0, 1) * 4095).astype(np.uint16)
        PILImage.fromarray(q).save(folder / f"{v}.png")
    _predict(ckpt, folder, tmp_path / "crop", "fit=crop", "scale=4095")
    said = capsys.readouterr().out
    assert "intensity: value / 4095 (given by scale=)" in said
    assert "size: 64x48 -> 32x32 by crop (central 48x48)" in said
    assert "rig: none given" in said
    _predict(ckpt, folder, tmp_path / "pad", "fit=pad")
    said = capsys.readouterr().out
    assert "intensity: value / 65535 (16-bit integers; override with scale=)" in said
    assert "size: 64x48 -> 32x32 by pad (padded to 64x64)" in said


def test_fit_keeps_geometry():
    a = np.arange(6 * 8, dtype=np.float32).reshape(1, 6, 8)
    cropped, _ = fit_to(a, (6, 6), "crop")
    np.testing.assert_array_equal(cropped, a[:, :, 1:7])
    padded, _ = fit_to(a, (8, 8), "pad")
    assert padded[0, 0].sum() == 0 and np.array_equal(padded[:, 1:7], a)


def test_many_scenes_with_provenance_and_valid_points(trained, tiny_dataset, tmp_path):
    ckpt = trained[1]["best_checkpoint"]
    captures = tmp_path / "captures"
    for sid in ("000004", "000005", "000006"):
        for v, img in _views(tiny_dataset / "scenes" / sid).items():
            _save(captures / f"part_{sid}", v, img, "png16")
    results = _predict(ckpt, str(captures / "part_*"), tmp_path / "out")
    assert [r["depth"].parent.name for r in results] == [
        "part_000004",
        "part_000005",
        "part_000006",
    ]
    header = OpenEXR.File(str(results[0]["depth"]), header_only=True).header()
    assert header["unit"] == "mm" and header["odmv_model"].endswith(".ckpt")
    assert results[0]["preview"].read_bytes()[:4] == b"\x89PNG"
    everything = _predict(ckpt, captures / "part_000004", tmp_path / "all", "drop_unlit=false")
    lit_only = _ply_vertices(results[0]["points"])
    assert _ply_vertices(everything[0]["points"]) == 32 * 32
    # the image corners are lit by no projector of the rig: their points are dropped
    assert 0.5 * 32 * 32 < lit_only < 32 * 32


def _ply_vertices(path):
    head = path.read_bytes().split(b"end_header\n")[0].decode()
    return int(next(x for x in head.splitlines() if x.startswith("element vertex")).split()[-1])


def test_classical_method_on_a_scene_and_on_loose_images(tiny_dataset, tmp_path):
    scene = tiny_dataset / "scenes" / "000004"
    cfg = compose_config("predict", ["method=psp", f"input={scene}", f"out={tmp_path / 'a'}"])
    (done,) = predict(cfg)
    depth = read_channel(done["depth"], "Z")
    truth = read_channel(scene / "depth.exr", "Z")
    ok = np.isfinite(depth)
    assert ok.mean() > 0.6 and np.abs(depth - truth)[ok].mean() < 0.1  # mm
    loose = tmp_path / "loose"
    loose.mkdir()
    for f in (scene / "fringe").glob("*_f*_s*.exr"):
        shutil.copy(f, loose / f.name)
    cfg = compose_config(
        "predict",
        ["method=psp", f"input={loose}", f"out={tmp_path / 'b'}", f"manifest={tiny_dataset}"],
    )
    np.testing.assert_array_equal(read_channel(predict(cfg)[0]["depth"], "Z"), depth)
    done = subprocess.run(  # no calibration: the phase only, said as the app's summary
        [sys.executable, "-m", "odmv.predict", "method=psp", f"input={loose}", "out=c"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "phase (rad): c/right_phase.exr"


def test_psp_on_a_dataset_without_sequences_says_what_it_needs(tmp_path):
    """As a user runs it: one line naming the fix, and no folder left behind."""
    from odmv.sim.writer import SimSettings, simulate

    ds = tmp_path / "ds"
    simulate(SimSettings(out=ds, scenes=1, height_px=32, width_px=32, images="training"),
             workers=1, progress=False)  # fmt: skip
    done = subprocess.run(
        [sys.executable, "-m", "odmv.predict", "method=psp", f"input={ds}/scenes/000000"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 2
    assert "holds the network's images only (images=training); render it with images=full" in (
        done.stdout + done.stderr
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_bad_images_are_named(tmp_path):
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[..., 0] = 200
    PILImage.fromarray(rgb).save(tmp_path / "colour.png")
    with pytest.raises(ImageError, match=r"colour.png: a colour image"):
        read_image(tmp_path / "colour.png")
    (tmp_path / "noise.png").write_bytes(np.random.default_rng(0).bytes(100))
    with pytest.raises(ImageError, match=r"noise.png: not a readable image"):
        read_image(tmp_path / "noise.png")
    with pytest.raises(ImageError, match=r"missing.tif: no such file"):
        read_image(tmp_path / "missing.tif")


def test_an_opencv_calibration_gives_the_rig_it_describes(trained, tiny_dataset, tmp_path):
    import yaml

    from odmv.io.calibration import CalibrationError, load_calibration
    from odmv.io.manifest import load_manifest

    rig = load_manifest(tiny_dataset).rig
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(calibration_of(rig, 64, 64)))
    calibrated = load_calibration(path)
    np.testing.assert_allclose(calibrated.camera_at(32, 32).P, rig.camera_at(32, 32).P, atol=1e-9)
    for name, p in rig.projectors().items():
        np.testing.assert_allclose(calibrated.projectors()[name].P, p.P, atol=1e-6)
    # the net's reference phase and point cloud come out the same as with the dataset's rig
    ckpt = trained[1]["best_checkpoint"]
    folder = tmp_path / "images"
    for v, img in _views(tiny_dataset / "scenes" / "000004").items():
        _save(folder, v, img, "exr")
    (a,) = _predict(ckpt, folder, tmp_path / "a", f"calibration={path}")
    (b,) = _predict(ckpt, folder, tmp_path / "b", f"manifest={tiny_dataset}")
    np.testing.assert_allclose(read_channel(a["depth"], "Z"), read_channel(b["depth"], "Z"))
    assert a["points"].read_bytes() == b["points"].read_bytes()
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "camera: {image_size: [64, 64], K: [[1, 0]]}\nprojectors: {}\nreference_plane_mm: 150\n"
    )
    with pytest.raises(CalibrationError, match=r"bad.yaml: camera.K must be a finite 3x3 array"):
        load_calibration(bad)


def test_points_are_coloured_by_the_uniform_images(trained, tiny_dataset, tmp_path):
    ckpt = trained[1]["best_checkpoint"]
    scene = tiny_dataset / "scenes" / "000004"
    (coloured,) = _predict(ckpt, scene, tmp_path / "a", "drop_unlit=false")
    (plain,) = _predict(ckpt, scene, tmp_path / "b", "drop_unlit=false", "colour=false")
    head, body = coloured["points"].read_bytes().split(b"end_header\n")
    assert b"property uchar red" in head and len(body) == 32 * 32 * 15
    rows = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    assert rows["rgb"].max() > 100 and (rows["rgb"][:, 0] == rows["rgb"][:, 2]).all()
    assert b"uchar" not in plain["points"].read_bytes().split(b"end_header")[0]
