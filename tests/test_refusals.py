"""Bad settings and bad data refused before anything is written, in one line naming the key or
file and what is allowed; a refused command leaves no folder it created (and every folder it
did not create) behind; records read from anywhere."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import one_line_error, run_app, tiny_overrides

from odmv.io.exr import read_channel, write_exr
from odmv.io.runfolder import FAILED, METRICS, recorded_dataset
from odmv.study.results import find_runs


@pytest.mark.parametrize(
    "args, expected",
    [
        (["resolution=0"], "error: resolution=0: image sizes are at least 1 px"),
        (["resolution=-64"], "error: resolution=-64: image sizes are at least 1 px"),
        (["resolution=[64,abc]"], "error: resolution='abc': not a whole number"),
        (["views=[]"], "error: views: no view named; name at least one of right, down, left, up"),
        (["scenes=abc"], "error: scenes='abc': not a whole number; render at least one scene"),
        (["seed=-1"], "error: seed=-1: 0 or more"),
    ],
)
def test_simulate_refuses_bad_sizes_and_views_leaving_no_folder(args, expected, tmp_path):
    line = one_line_error(run_app("simulate", "out=ds", "scenes=2", *args, cwd=tmp_path))
    assert line == expected or line.startswith(expected)
    assert not (tmp_path / "ds").exists()


def test_an_unquoted_non_ascii_path_says_how_to_quote_it(tmp_path):
    line = one_line_error(run_app("simulate", "out=données", "scenes=2", cwd=tmp_path))
    assert line == """error: out: Hydra reads this value only quoted; write 'out="données"'"""


@pytest.mark.parametrize(
    "args, expected",
    [
        (["trainer.max_epochs=abc"], "error: trainer.max_epochs='abc': not a whole number; at"),
        (["seed=-1"], "error: seed=-1: a seed is 0 or more"),
        (["views=[]"], "error: data.views: no view named; name at least one of right, down,"),
        (["data.batch_size=0"], "error: data.batch_size=0: at least 1"),
    ],
)
def test_train_names_the_key_and_what_it_takes(args, expected, tiny_dataset, tmp_path):
    run = tmp_path / "run"
    line = one_line_error(run_app("train", *tiny_overrides(tiny_dataset, run), *args, cwd=tmp_path))
    assert line.startswith(expected)
    assert not run.exists()


def test_an_empty_test_split_is_refused_before_the_first_epoch(dataset_copy, tmp_path):
    path = dataset_copy / "manifest.json"
    manifest = json.loads(path.read_text())
    for scene in manifest["scenes"]:
        scene["split"] = "train" if scene["split"] == "test" else scene["split"]
    path.write_text(json.dumps(manifest))
    run = tmp_path / "run"
    done = run_app("train", *tiny_overrides(dataset_copy, run), cwd=tmp_path)
    line = one_line_error(done)
    assert line.startswith(f"error: {dataset_copy}: no test scenes (train 9, val 1, test 0); its")
    assert "train with test=false" in line
    assert not run.exists() and "epoch 1/" not in done.stdout


def test_black_fringes_are_found_by_the_validator_and_refused_by_training(dataset_copy, tmp_path):
    manifest = json.loads((dataset_copy / "manifest.json").read_text())
    sid = next(s["id"] for s in manifest["scenes"] if s["split"] == "train")
    for path in sorted((dataset_copy / "scenes" / sid / "fringe").glob("up_f*.exr")):
        write_exr(path, {"Y": np.zeros_like(read_channel(path, "Y"))})
    done = run_app("validate", str(dataset_copy), cwd=tmp_path)
    assert done.returncode != 0 and "up_f0_s00.exr: no fringe" in done.stdout
    run = tmp_path / "run"
    line = one_line_error(run_app("train", *tiny_overrides(dataset_copy, run), cwd=tmp_path))
    assert f"scenes/{sid}/fringe/up_f" in line and ": no fringe (1-99 %" in line
    assert not run.exists()


@pytest.mark.parametrize(
    "edit, expected",
    [
        (("geometry", "camera", "K", 0, 0), "rig.geometry.camera.K is [[0, "),
        (
            ("spec", "projector", "distance_mm"),
            "rig.spec.projector.distance_mm: -167.0; a positive",
        ),
        (("spec", "camera", "pixel_um"), "rig.spec.camera.pixel_um: -3.2; a positive number"),
    ],
)
def test_a_manifest_rig_that_the_project_would_ignore_or_divide_by_is_refused(
    edit, expected, tiny_dataset, tmp_path
):
    copy = tmp_path / "ds"
    copy.mkdir()
    (copy / "scenes").symlink_to(tiny_dataset / "scenes")
    manifest = json.loads((tiny_dataset / "manifest.json").read_text())
    node = manifest["rig"]
    for key in edit[:-1]:
        node = node[key]
    node[edit[-1]] = 0 if edit[0] == "geometry" else -node[edit[-1]]
    (copy / "manifest.json").write_text(json.dumps(manifest))
    done = run_app("validate", str(copy), cwd=tmp_path)
    assert done.returncode != 0 and expected in done.stdout, done.stdout


def test_refused_predict_and_export_leave_no_folder_they_made_and_every_one_they_did_not(
    trained, tiny_dataset, tmp_path
):
    ckpt = trained[1]["best_checkpoint"]
    scene = next((tiny_dataset / "scenes").iterdir())
    done = run_app("predict", f"ckpt_path={ckpt}", f"input={scene}", "out=p", "views=[front]",
                cwd=tmp_path)  # fmt: skip
    assert "views=['front']: no view 'front'; the net knows only right, down, left, up" in (
        one_line_error(done)
    )
    one_line_error(run_app("export", "ckpt_path=missing.ckpt", "out=e", cwd=tmp_path))
    assert not (tmp_path / "p").exists() and not (tmp_path / "e").exists()
    (tmp_path / "mine").mkdir()
    one_line_error(run_app("export", "ckpt_path=missing.ckpt", "out=mine", cwd=tmp_path))
    one_line_error(run_app("predict", "ckpt_path=missing.ckpt", f"input={scene}", "out=mine",
                         cwd=tmp_path))  # fmt: skip
    assert (tmp_path / "mine").is_dir()


def test_a_relative_dataset_in_a_record_is_found_from_any_working_folder(tmp_path, monkeypatch):
    (tmp_path / "work" / "data" / "tiny").mkdir(parents=True)
    run = tmp_path / "work" / "outputs" / "run"
    run.mkdir(parents=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # the page is made from another folder than the training
    found = recorded_dataset({"dataset": "data/tiny"}, run)
    assert found == tmp_path / "work" / "data" / "tiny"


@pytest.mark.slow
def test_a_checkpoint_moved_with_its_dataset_evaluates_and_exports_from_anywhere(
    tiny_dataset, tmp_path
):
    """A checkout moved (or copied to another machine) with its data/ and outputs/: the
    checkpoint's dataset path is stale, the dataset is found beside the run."""
    work, elsewhere = tmp_path / "work", tmp_path / "elsewhere"
    shutil.copytree(tiny_dataset, work / "data" / "tiny")
    elsewhere.mkdir()
    done = run_app("train", *tiny_overrides("data/tiny", "outputs/run"), cwd=work)
    assert done.returncode == 0, done.stderr[-2000:]
    work = work.rename(tmp_path / "moved")
    ckpt = (
        work
        / "outputs"
        / "run"
        / json.loads((work / "outputs/run" / METRICS).read_text())["best_checkpoint"]
    )
    done = run_app("evaluate", f"ckpt_path={ckpt}", "figures=0", "hydra.run.dir=ev", cwd=elsewhere)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"on the test split of {work / 'data' / 'tiny'}" in done.stdout
    done = run_app("export", f"ckpt_path={ckpt}", "out=e", cwd=elsewhere)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"for the run's dataset {work / 'data' / 'tiny'}" in done.stdout


def test_study_verbs_refuse_missing_runs_in_one_line(tmp_path):
    for args in (["summarize", "X=/missing*"], ["heights", "/missing"], ["shadows", "A=/no*"],
                 ["split", "/missing"]):  # fmt: skip
        line = one_line_error(run_app("study", *args, cwd=tmp_path))
        assert "/missing" in line or "/no*" in line


def test_the_report_counts_failed_and_killed_runs_as_unfinished(trained, tmp_path):
    shutil.copytree(trained[0], tmp_path / "done")
    failed = tmp_path / "failed"
    (failed / ".hydra").mkdir(parents=True)
    (failed / FAILED).write_text("Interrupted: stopped by SIGTERM in epoch 3\n")
    killed = tmp_path / "killed" / "checkpoints"
    killed.mkdir(parents=True)
    (killed / "last.ckpt").write_bytes(b"")
    runs, pending = find_runs([tmp_path])
    assert [r.folder.name for r in runs] == ["done"] and (tmp_path / "done" / METRICS).is_file()
    assert [p.name for p in pending] == ["failed", "killed"]
    done = run_app("report", f"runs=[{tmp_path}]", f"out={tmp_path / 'report'}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    text = Path(tmp_path / "report" / "tables.md").read_text()
    assert "1 finished" in text and "2 unfinished" in text and "(failed: failed.txt)" in text
