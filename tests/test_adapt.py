"""Label-free adaptation: the depth -> projector projection against the simulator's, the
consistency loss on noise-free twin scenes (near zero at the truth, rising with a depth offset,
its gradient pointing back), the calibration check against a turned projector, and
``adapt=true`` on a dataset whose depth files are gone."""

import csv
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from helpers import CLEAN, RIG, compose_config, tiny_overrides
from omegaconf import OmegaConf

from odmv.classical.geometry import coord_from_depth, phase_from_depth, triangulation_maps
from odmv.data.classical import classical_depths
from odmv.data.dataset import DataError, check_spec, load_scene
from odmv.io.manifest import (
    DEPTH_FILE,
    FOOTPRINT_FILE,
    LIT_FILE,
    PROJ_COORD_FILE,
    FringeSpec,
    load_manifest,
)
from odmv.io.validation import validate
from odmv.rig import VIEW_NAMES
from odmv.sim.shifts import Shift
from odmv.sim.writer import SimSettings, simulate
from odmv.training.adaptation import StaleCalibrationError, check_calibration
from odmv.training.configs import adapted_config
from odmv.training.consistency import (
    SECOND_HARMONIC_SHARE,
    TARGET_DEFAULTS,
    ConsistencySettings,
    chosen_fit,
    consistency_loss,
    fringe_fit,
    harmonic_sums,
    view_offsets_mm,
)
from odmv.training.evaluation import evaluate
from odmv.training.module import load_module
from odmv.training.run import train

SETTINGS = ConsistencySettings()


def test_depth_projects_into_each_projector_as_the_simulator_projects():
    h = w = 64
    maps = torch.from_numpy(triangulation_maps(RIG, VIEW_NAMES, h, w, 240.0, 0, 12))[None]
    cam = RIG.camera_at(w, h)
    origin, d = cam.centre_rays()
    depth = 141.0 + 12.0 * np.random.default_rng(0).random((h, w))  # mm, plane to 12 mm parts
    # the camera-axis depth of a point along each pixel's ray: z = (X - C) . r_3
    t = depth / (d @ cam.R[2])
    points = origin + t[..., None] * d
    got = coord_from_depth(torch.from_numpy(depth).float()[None, None], maps)[0].double()
    for i, proj in enumerate(RIG.projectors().values()):
        uv = proj.project(points)
        want = uv[..., 0] if proj.phase_axis == "u" else uv[..., 1]
        assert np.abs(got[i].numpy() - want).max() < 1e-3  # projector px


@pytest.fixture(scope="module")
def clean_scenes(tmp_path_factory):
    """Four noise-free 64 px twin scenes whose input is the 240 px fringe (10 camera px)."""
    out = tmp_path_factory.mktemp("clean") / "clean"
    settings = SimSettings(
        out=out, scenes=4, height_px=64, width_px=64, seed=1, images="training",
        fringe=FringeSpec(train_frequency=1), render=CLEAN,
    )  # fmt: skip
    simulate(settings, workers=1, progress=False)
    return out


def _scene(root, sid):
    m = load_manifest(root)
    spec = check_spec(m, VIEW_NAMES, 64, None, None)
    maps = triangulation_maps(m.rig, VIEW_NAMES, 64, 64, spec.period_px, spec.step, spec.n_steps)
    raw = load_scene(m, sid, spec)
    as_batch = (torch.from_numpy(x)[None] for x in (raw["fringes"], raw["depth_mm"], maps))
    return tuple(as_batch)


@pytest.mark.parametrize("sid", ["000001", "000003"])
def test_the_loss_is_least_at_the_true_depth_and_pulls_back_to_it(clean_scenes, sid):
    fringes, truth, maps = _scene(clean_scenes, sid)
    error, amplitude, r2 = fringe_fit(fringes, phase_from_depth(truth, maps), 5)
    used = amplitude >= SETTINGS.min_amplitude
    assert used.float().mean() > 0.5
    # the depth's own fringe explains the image, most windows to 0.02 rad (0.8 projector px):
    # the irradiance falling off along each projector's phase axis, which the window's
    # constant amplitude reads as a phase, biases every view alike by about -0.010 rad
    assert error[used].abs().median() < 0.02 and r2[used].median() > 0.98
    losses, back = [], []
    for offset_mm in (0.0, 0.1, 0.3, 1.0):
        depth = (truth + offset_mm).requires_grad_(True)
        loss = consistency_loss(depth, fringes, maps, SETTINGS)["loss"]
        loss.backward()
        losses.append(float(loss))
        moved = depth.grad != 0
        back.append(float((depth.grad[moved] > 0).float().mean()))  # descent lowers the depth
    assert losses == sorted(losses) and losses[0] < 0.2 * losses[-1]
    assert back[2] > 0.8 and back[3] > 0.8


def test_the_fit_with_harmonics_reads_a_gamma_distorted_fringe():
    """Projector gamma 2.2 turns the fringe into a sum of harmonics. Inside a window the
    second leaks into a sinusoid fit's phase (0.2 rad at 5 px); fitted too, it does not."""
    y, x = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    phase = (2 * torch.pi * x / 10.3 + 0.002 * (y - 32) ** 2)[None, None]
    image = 0.1 + 0.8 * ((1 + torch.cos(phase)) / 2) ** 2.2
    inner = (..., slice(8, -8), slice(8, -8))  # away from the border's smaller windows
    sinusoid_fit = fringe_fit(image, phase, 5)[0][inner].abs().median()
    harmonic_fit = fringe_fit(image, phase, 9, harmonics=2)[0][inner].abs().median()
    assert sinusoid_fit > 0.1 and harmonic_fit < 0.005  # rad
    undistorted = 0.1 + 0.4 * (1 + torch.cos(phase))
    assert fringe_fit(undistorted, phase, 9, harmonics=2)[0][inner].abs().max() < 1e-4
    with pytest.raises(ValueError, match="harmonics: 2 .* window_px is 3"):
        ConsistencySettings(window_px=3, harmonics=2)


def test_the_fit_is_chosen_by_the_fringes_second_harmonic(clean_scenes, tmp_path):
    """At the true depth, the twin's sinusoid carries almost no second harmonic and projector
    gamma 2.2 a large one: harmonics=auto fits one harmonic to the first, two (in a window of
    about a fringe period) to the second."""
    gamma = tmp_path / "gamma"
    settings = SimSettings(
        out=gamma, scenes=2, height_px=64, width_px=64, seed=1, images="training",
        fringe=FringeSpec(train_frequency=1), render=CLEAN, shift=Shift("gamma", 2.2, 0),
    )  # fmt: skip
    simulate(settings, workers=1, progress=False)
    auto = ConsistencySettings(harmonics="auto")
    shares = {}
    for name, root in (("sinusoid", clean_scenes), ("gamma", gamma)):
        fringes, truth, maps = _scene(root, "000001")
        second, first = harmonic_sums(truth, fringes, maps, auto)
        shares[name] = float(second.sum() / first.sum())
    assert shares["sinusoid"] < 0.5 * SECOND_HARMONIC_SHARE < SECOND_HARMONIC_SHARE
    assert shares["gamma"] > 1.5 * SECOND_HARMONIC_SHARE
    fits = {k: chosen_fit(auto, v) for k, v in shares.items()}
    assert (fits["sinusoid"].harmonics, fits["sinusoid"].window_px) == (1, 5)
    assert (fits["gamma"].harmonics, fits["gamma"].window_px) == (2, 9)
    with pytest.raises(ValueError, match="harmonics: three must be auto or at least 1"):
        ConsistencySettings(harmonics="three")


def test_a_turned_projector_makes_the_views_disagree(clean_scenes, tmp_path):
    """At the true depth through the nominal calibration, the views of the nominal twin ask
    for the same (no) change; with the projectors turned by 0.1 degree after calibrating they
    ask for changes of their own, which the check refuses."""
    turned = tmp_path / "turned"
    m = load_manifest(clean_scenes)
    settings = SimSettings(
        out=turned, scenes=4, height_px=64, width_px=64, seed=1, images="training",
        fringe=FringeSpec(train_frequency=1), render=CLEAN,
        shift=Shift("projector_rotation", 0.1, 0),
    )  # fmt: skip
    simulate(settings, workers=1, progress=False)
    spreads = {}
    for name, root in (("nominal", clean_scenes), ("turned", turned)):
        sums = np.zeros(4)
        for sid in ("000000", "000001", "000002", "000003"):
            fringes, truth, maps = _scene(root, sid)
            mean, _ = view_offsets_mm(truth, fringes, maps, SETTINGS)
            sums += mean.numpy() / 4
        spreads[name] = float(np.std(sums))
        offsets = dict(zip(m.views, sums.tolist(), strict=True))
        if name == "nominal":
            assert check_calibration(offsets, SETTINGS.stale_mm, root) < 0.02
        else:
            with pytest.raises(StaleCalibrationError, match="views disagree.*recalibrate"):
                check_calibration(offsets, SETTINGS.stale_mm, root)
    assert spreads["turned"] > 5 * spreads["nominal"]


@pytest.fixture(scope="module")
def twin240(tmp_path_factory):
    """Ten 64 px twin scenes whose network image is the 240 px fringe (as the mini protocol's)."""
    out = tmp_path_factory.mktemp("twin240") / "twin240"
    settings = SimSettings(
        out=out, scenes=10, height_px=64, width_px=64, seed=1, images="training",
        fringe=FringeSpec(train_frequency=1),
    )  # fmt: skip
    simulate(settings, workers=1, progress=False)
    return out


@pytest.fixture(scope="module")
def unlabelled(twin240, tmp_path_factory):
    """Those scenes without their ground truth: fringes and calibration only."""
    out = shutil.copytree(twin240, tmp_path_factory.mktemp("unlabelled") / "data")
    for scene in (out / "scenes").iterdir():
        for name in (DEPTH_FILE, LIT_FILE, PROJ_COORD_FILE, FOOTPRINT_FILE):
            (scene / name).unlink(missing_ok=True)
    return out


@pytest.fixture(scope="module")
def base_run(twin240, tmp_path_factory):
    out = tmp_path_factory.mktemp("base")
    ov = tiny_overrides(twin240, out, "head=phase", "reference=true")
    train(compose_config("train", ov))
    return out


def test_a_dataset_without_depth_is_refused_for_training_and_read_without_labels(unlabelled):
    m = load_manifest(unlabelled)
    with pytest.raises(DataError, match=f"{DEPTH_FILE}"):
        load_scene(m, "000000", check_spec(m, VIEW_NAMES, 64, None, None))
    raw = load_scene(m, "000000", check_spec(m, VIEW_NAMES, 64, None, None, labels=False))
    assert set(raw) == {"fringes"} and raw["fringes"].shape == (4, 64, 64)
    report = validate(unlabelled)
    assert report.ok and "no ground truth" in report.summary(unlabelled)


def test_a_dataset_missing_some_scenes_depth_is_named(twin240, tmp_path):
    partial = shutil.copytree(twin240, tmp_path / "partial")
    (partial / "scenes" / "000002" / DEPTH_FILE).unlink()
    report = validate(partial)
    assert [p for p in report.problems if DEPTH_FILE in p] == [
        f"{partial / 'scenes' / '000002' / DEPTH_FILE}: no such file"
    ]


def test_adapt_fine_tunes_a_run_on_fringes_alone(base_run, unlabelled, twin240, tmp_path):
    out = tmp_path / "adapted"
    overrides = [
        "adapt=true",
        f"init_from={base_run}",
        f"root={unlabelled}",
        f"paths.output_dir={out}",
        "adaptation.epochs=2",
        "adaptation.check_calibration=false",  # a one-epoch net's depth says nothing of the rig
        "trainer.limit_train_batches=2",
        "trainer.enable_progress_bar=false",
    ]
    cfg = adapted_config(compose_config("train", overrides), overrides)
    assert cfg.model.net.base_width == 4 and cfg.data.resolution == 32  # the base run's
    assert cfg.data.labels is False and cfg.callbacks.checkpoint.monitor == "val/loss"
    metrics = train(cfg)
    record = json.loads((out / "metrics.json").read_text())
    assert record["adapted_from"].endswith(".ckpt") and set(record["view_offsets_mm"]) == set(
        VIEW_NAMES
    )
    assert record["target"] == "fringes"  # auto, on one image per projector
    assert np.isfinite(metrics["val/loss"])
    # harmonics=auto (the default) chose a fit and trains as a run that names it
    window, harmonics = record["fit"].split(":")
    assert 0 <= record["second_harmonic_share"] < 1 and harmonics in ("1", "2")
    named = [*overrides[:3], f"paths.output_dir={tmp_path / 'named'}", *overrides[4:]]
    named += [f"adaptation.harmonics={harmonics}", f"adaptation.window_px={window}"]
    again = train(adapted_config(compose_config("train", named), named))
    assert again["val/loss"] == metrics["val/loss"]
    module = load_module(out / record["best_checkpoint"])
    assert module.adapt is None and module.hparams.adapt["anchor"] == SETTINGS.anchor
    # where labels exist, the adapted net is measured like any
    ev = compose_config("evaluate", [f"ckpt_path={out / record['best_checkpoint']}",
                                     f"root={twin240}", f"paths.output_dir={tmp_path / 'ev'}",
                                     "figures=0", "progress=false"])  # fmt: skip
    scores = evaluate(ev, [f"root={twin240}"])
    assert np.isfinite(scores["test/mae_mm"])


def test_adapt_replays_the_twin_it_was_trained_on(base_run, unlabelled, tmp_path):
    """adaptation.replay: every step also takes a batch of the base run's own labelled
    training scenes under the base's loss."""
    out = tmp_path / "replayed"
    overrides = ["adapt=true", f"init_from={base_run}", f"root={unlabelled}",
                 f"paths.output_dir={out}", "adaptation.epochs=1", "adaptation.replay=0.5",
                 "adaptation.check_calibration=false", "trainer.limit_train_batches=2",
                 "trainer.enable_progress_bar=false"]  # fmt: skip
    cfg = adapted_config(compose_config("train", overrides), overrides)
    assert cfg.data.replay.root == str(load_manifest(cfg.data.replay.root).root)
    train(cfg)
    logged = list(csv.DictReader((out / "csv" / "metrics.csv").open()))
    replay = [float(r["train/loss_replay"]) for r in logged if r.get("train/loss_replay")]
    assert replay and all(np.isfinite(replay))


def test_adapt_without_the_twin_to_replay_says_so(base_run, unlabelled, tmp_path):
    """Replay is on by default; where the base run's training data is gone, one line says what
    is missing and how to adapt without it."""
    from omegaconf import OmegaConf

    run = shutil.copytree(base_run, tmp_path / "moved")
    saved = OmegaConf.load(run / ".hydra" / "config.yaml")
    saved.data.root = str(tmp_path / "gone")
    OmegaConf.save(saved, run / ".hydra" / "config.yaml")
    overrides = [
        "adapt=true",
        f"init_from={run}",
        f"root={unlabelled}",
        f"paths.output_dir={tmp_path}",
    ]
    with pytest.raises(ValueError, match=r"gone: the twin .* adaptation.replay=0 to adapt"):
        adapted_config(compose_config("train", overrides), overrides)
    without = [*overrides, "adaptation.replay=0"]
    cfg = adapted_config(compose_config("train", without), without)
    assert "replay" not in cfg.data or not cfg.data.replay


def test_the_calibration_check_measures_with_the_sinusoid_fit(base_run, unlabelled, tmp_path):
    """Whatever fit the adaptation chose, the check's per-view offsets come from the sinusoid
    fit in adaptation.window_px (the two-harmonic fit's are too unsteady to compare views)."""
    from dataclasses import replace

    from odmv.training.adaptation import view_offsets
    from odmv.training.run import build

    overrides = ["adapt=true", f"init_from={base_run}", f"root={unlabelled}",
                 f"paths.output_dir={tmp_path}", "adaptation.replay=0"]  # fmt: skip
    dm, module, _ = build(adapted_config(compose_config("train", overrides), overrides))
    dm.prepare_data()
    dm.setup("fit")
    module.norm = dm.norm

    def offsets(harmonics, fit_window, check_window):
        module.adapt = replace(module.adapt, harmonics=harmonics, window_px=fit_window)
        return view_offsets(module, dm.val_dataloader(), list(dm.spec.views), check_window)

    sinusoid = offsets(1, 5, 5)
    assert offsets(2, 9, 5) == sinusoid and offsets(1, 9, 9) != sinusoid


def test_an_adapted_run_resumes_on_the_users_data(base_run, sequences, tmp_path):
    """The app, as a user types it: the adapted run's folder keeps the config it ran (the
    user's dataset, the target's settings resolved), so resume=RUN continues that
    fine-tune rather than training on the twin of the command line's defaults."""
    run = tmp_path / "adapted"
    app = [sys.executable, "-m", "odmv.train"]
    first = subprocess.run(
        [*app, "adapt=true", f"init_from={base_run}", f"root={sequences[1]}",
         f"paths.output_dir={run}", "adaptation.epochs=1", "adaptation.replay=0",
         "trainer.enable_progress_bar=false"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert first.returncode == 0, first.stderr[-2000:]
    saved = OmegaConf.load(run / ".hydra" / "config.yaml")
    assert saved.data.root == str(sequences[1].resolve()) and saved.adaptation.lr == 3e-4
    kept = ("calibration_check", "view_offsets_mm", "view_spread_mm")
    checked = {k: json.loads((run / "metrics.json").read_text())[k] for k in kept}
    again = subprocess.run([*app, f"resume={run}", "trainer.max_epochs=2"], cwd=tmp_path,
                           capture_output=True, text=True, timeout=600)  # fmt: skip
    assert again.returncode == 0, again.stderr[-2000:]
    assert f"continuing {run}" in again.stdout
    record = json.loads((run / "metrics.json").read_text())
    assert record["dataset"] == str(sequences[1].resolve()) and record["target"] == "classical"
    assert {k: record[k] for k in kept} == checked  # the check of the starting net, kept
    rows = list(csv.DictReader((run / "csv" / "metrics.csv").open()))
    assert {r["epoch"] for r in rows if r.get("val/loss")} == {"0", "1"}


def test_adapt_names_what_it_lacks(base_run, unlabelled):
    for overrides, message in (
        (["adapt=true", f"root={unlabelled}"], "init_from=RUN"),
        (["adapt=true", f"init_from={base_run}"], "root=DATASET"),
    ):
        with pytest.raises(ValueError, match=message):
            adapted_config(compose_config("train", overrides), overrides)


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    """Six of twin240's scenes with every projector's full sequences, and without their
    ground truth; their labelled copy beside them."""
    out = tmp_path_factory.mktemp("sequences")
    settings = SimSettings(
        out=out / "labelled", scenes=6, height_px=64, width_px=64, seed=1, images="full",
        fringe=FringeSpec(train_frequency=1),
    )  # fmt: skip
    simulate(settings, workers=1, progress=False)
    bare = shutil.copytree(out / "labelled", out / "bare")
    for scene in (bare / "scenes").iterdir():
        for name in (DEPTH_FILE, LIT_FILE, PROJ_COORD_FILE, FOOTPRINT_FILE):
            (scene / name).unlink(missing_ok=True)
    return out / "labelled", bare


def test_the_classical_target_is_reconstructed_from_the_sequences_alone(sequences):
    labelled, bare = sequences
    m = load_manifest(labelled)
    ids = [s["id"] for s in m.scenes]
    depths, _ = classical_depths(load_manifest(bare), ids, (64, 64))
    spec = check_spec(m, VIEW_NAMES, 64, None, None)
    errors, covered = [], []
    for sid in ids:
        truth = load_scene(m, sid, spec)["depth_mm"][0]
        ok = np.isfinite(depths[sid])
        errors.append(np.abs(depths[sid] - truth)[ok])
        covered.append(ok.mean())
    # phase shifting on the noisy twin: a few hundredths of a mm where it reconstructs
    assert np.mean(np.concatenate(errors)) < 0.05 and np.mean(covered) > 0.6


def test_adapt_fits_the_classical_depth_of_the_users_sequences(base_run, sequences, tmp_path):
    """adaptation.target=auto (the default) on a dataset with the full sequences: the net
    fitted to the depth phase shifting reconstructs from the unlabelled scenes' sequences, the
    share reconstructed recorded."""
    out = tmp_path / "classical"
    overrides = ["adapt=true", f"init_from={base_run}", f"root={sequences[1]}",
                 f"paths.output_dir={out}", "adaptation.epochs=2", "adaptation.replay=0",
                 "adaptation.check_calibration=false",
                 "trainer.enable_progress_bar=false"]  # fmt: skip
    cfg = adapted_config(compose_config("train", overrides), overrides)
    assert cfg.data.augment is None and cfg.data.labels is False
    metrics = train(cfg)
    record = json.loads((out / "metrics.json").read_text())
    assert record["target"] == "classical" and 0.3 < record["classical_covered"] <= 1
    assert np.isfinite(metrics["val/loss"])
    logged = list(csv.DictReader((out / "csv" / "metrics.csv").open()))
    fitted = [float(r["train/loss_classical"]) for r in logged if r.get("train/loss_classical")]
    assert fitted and all(np.isfinite(fitted))


def test_auto_settings_follow_the_target(base_run, unlabelled, sequences, tmp_path):
    """lr, anchor and replay left at auto take the chosen target's defaults; a value given on
    the command line wins; the supervised fine-tune takes its own lr."""
    start = ["adapt=true", f"init_from={base_run}", f"paths.output_dir={tmp_path}"]
    for root, extra, defaults, given in (
        (unlabelled, [], "fringes", {}),
        (sequences[1], [], "classical", {}),
        (sequences[1], ["adaptation.replay=0"], "classical", {"replay": 0}),
        (sequences[0], ["adaptation.supervised=true"], "supervised", {}),
    ):
        overrides = [*start, f"root={root}", *extra]
        cfg = adapted_config(compose_config("train", overrides), overrides)
        want = TARGET_DEFAULTS[defaults] | given
        assert {k: cfg.adaptation[k] for k in want} == want and cfg.optimizer.lr == want["lr"]
        assert cfg.adaptation.target == ("fringes" if root == unlabelled else "classical")
        assert bool(cfg.data.get("replay")) == (want["replay"] > 0 and defaults != "supervised")


@pytest.fixture(scope="module")
def turned_sequences(tmp_path_factory):
    """Four scenes' full sequences, without ground truth, from the twin with its projectors
    turned by 0.1 degree after it was calibrated (its manifest keeps the stale calibration)."""
    out = tmp_path_factory.mktemp("turned") / "data"
    settings = SimSettings(
        out=out, scenes=4, height_px=64, width_px=64, seed=2, images="full",
        fringe=FringeSpec(train_frequency=1), shift=Shift("projector_rotation", 0.1, 0),
    )  # fmt: skip
    simulate(settings, workers=1, progress=False)
    for scene in (out / "scenes").iterdir():
        for name in (DEPTH_FILE, LIT_FILE, PROJ_COORD_FILE, FOOTPRINT_FILE):
            (scene / name).unlink(missing_ok=True)
    return out


def test_the_projectors_own_depths_show_a_stale_calibration(sequences, turned_sequences):
    """Each projector's phase-shifting depth against the others': they agree through a
    calibration that describes the rig, and part where the projectors turned since."""
    spreads = {}
    for name, root in (("nominal", sequences[1]), ("turned", turned_sequences)):
        m = load_manifest(root)
        _, offsets = classical_depths(m, [s["id"] for s in m.scenes], (64, 64))
        assert list(offsets) == list(m.views)
        spreads[name] = np.std(list(offsets.values()))
    assert spreads["nominal"] < 0.01 and spreads["turned"] > 0.05


def test_a_one_view_net_is_not_fitted_through_a_stale_calibration(
    twin240, sequences, turned_sequences, tmp_path
):
    """A net that reads one view adapts to the classical depth of sequences from the rig as
    calibrated, checked on all four projectors the user captured; from the turned rig it is
    refused before training (a one-view net's own depth has nothing to compare)."""
    base = tmp_path / "unet"
    overrides = tiny_overrides(twin240, base, "model=unet", "head=phase", "reference=true")
    train(compose_config("train", [o for o in overrides if o != "model.net.blocks=1"]))
    start = ["adapt=true", f"init_from={base}", "adaptation.epochs=1", "adaptation.replay=0",
             "trainer.enable_progress_bar=false"]  # fmt: skip
    adapted = [*start, f"root={sequences[1]}", f"paths.output_dir={tmp_path / 'adapted'}"]
    train(adapted_config(compose_config("train", adapted), adapted))
    record = json.loads((tmp_path / "adapted" / "metrics.json").read_text())
    assert len(record["views"]) == 1 and record["calibration_check"] == "classical"
    assert len(record["view_offsets_mm"]) == 4 and record["view_spread_mm"] < 0.02
    refused = [*start, f"root={turned_sequences}", f"paths.output_dir={tmp_path / 'refused'}"]
    with pytest.raises(StaleCalibrationError, match=f"{turned_sequences}: the views disagree"):
        train(adapted_config(compose_config("train", refused), refused))
    assert not (tmp_path / "refused" / "metrics.json").exists()


def test_the_classical_target_needs_the_sequences(base_run, unlabelled, tmp_path):
    overrides = ["adapt=true", f"init_from={base_run}", f"root={unlabelled}",
                 f"paths.output_dir={tmp_path}", "adaptation.replay=0",
                 "adaptation.target=classical", "adaptation.check_calibration=false"]  # fmt: skip
    with pytest.raises(DataError, match=rf"{unlabelled}: the classical .*\(images=full\)"):
        train(adapted_config(compose_config("train", overrides), overrides))
    with pytest.raises(ValueError, match="adaptation.target: 'phase'"):
        ConsistencySettings(target="phase")


@pytest.mark.slow
def test_the_adapt_study_measures_adapted_and_supervised_nets(base_run, tmp_path):
    """The study (study=adapt's runner) on a tiny base: a shift's training set rendered, both
    fine-tunes run and scored, the table written, and a second call redoing nothing; an
    adaptation the check refuses (here at a zero threshold: a one-epoch net's depth explains
    no view) is recorded as refused."""
    from helpers import TRAIN
    from omegaconf import OmegaConf

    from odmv.study.adapt import run_adaptation

    def study(name, shift, *overrides):
        out = tmp_path / name
        settings = {"bases": [str(base_run)], "shifts": [shift], "scenes": 6, "test_scenes": 4}
        settings["variants"] = {"adapted": [], "replayed": ["adaptation.replay=1"]}
        cfg = OmegaConf.create(settings | {"overrides": ["adaptation.epochs=1", *overrides]})

        def run():
            run_adaptation(cfg, out / "runs", out / "out", None, TRAIN, "the study")

        run()
        rows = list(csv.DictReader((out / "out" / "adapt.csv").open()))
        assert [r["variant"] for r in rows] == ["adapted", "replayed"]
        return run, out / "out", rows[0]

    run, out, row = study("measured", "defocus:1.5", "adaptation.check_calibration=false")
    assert float(row["adapted_mm"]) > 0 and float(row["supervised_mm"]) > 0
    assert float(row["adapted_nominal_mm"]) > 0 and row["refused"] == "False"
    assert "| defocus:1.5 |" in (out / "adapt.md").read_text()
    scores = (out / "scores.json").stat().st_mtime_ns
    run()
    assert (out / "scores.json").stat().st_mtime_ns == scores

    _, out, row = study("refused", "projector_rotation:1", "adaptation.stale_mm=0")
    assert row["refused"] == "True" and float(row["supervised_mm"]) > 0
    refused = out / "runs" / f"{base_run.name}-adapted-projector_rotation_1" / "refused.txt"
    assert "views disagree" in refused.read_text()


def _captured(labelled, folder, frequencies, shift_sign=1):
    """The twin's sequences of ``frequencies`` as a rig saves them: 16-bit PNG per image,
    ``{view}_f{f}_s{n:02d}.png``, image n at the twin's step shift_sign n (mod N)."""
    from PIL import Image as PILImage

    from odmv.io.exr import read_channel
    from odmv.io.manifest import fringe_name

    m = load_manifest(labelled)
    for s in m.scenes:
        for view in m.views:
            for f, source in enumerate(frequencies):
                for n in range(m.fringe.steps):
                    twin = (
                        m.scene_dir(s["id"])
                        / "fringe"
                        / fringe_name(view, source, shift_sign * n % m.fringe.steps)
                    )
                    level = np.clip(read_channel(twin, "Y"), 0, 1) * 65535
                    path = folder / s["id"] / f"{view}_f{f}_s{n:02d}.png"
                    path.parent.mkdir(parents=True, exist_ok=True)
                    PILImage.fromarray(np.round(level).astype(np.uint16)).save(path)


@pytest.mark.slow
def test_the_own_rig_path_captures_convert_adapt_predict(base_run, sequences, tmp_path):
    """docs/dataset.md's own-rig path, rehearsed on the twin as a user types it: the twin's
    sequences saved as a rig saves them (shifted the other way), its calibration file written
    from the dataset, converted with the full sequences kept, the net (trained on the 240 px
    fringe) adapted to the classical target on its own 240 px images, and the adapted net
    predicting a converted scene. Captures without the 240 px fringe are refused."""
    from helpers import run_app

    from odmv.io.exr import read_channel

    labelled = sequences[0]
    _captured(labelled, tmp_path / "captures", (0, 1, 2), shift_sign=-1)
    done = run_app("calibration", str(labelled), "rig.yaml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    done = run_app("convert", "format=sequences", "src=captures", "calibration=rig.yaml",
                   "psp.shift_sign=-1", "out=mine", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    mine = load_manifest(tmp_path / "mine")
    assert mine.images == "full" and mine.views == load_manifest(labelled).views
    assert mine.fringe.periods_px == (1920.0, 240.0, 30.0) and mine.fringe.steps == 12
    ours = read_channel(mine.scene_dir("000000") / "fringe" / "right_f1_s03.exr", "Y")
    twin = read_channel(labelled / "scenes" / "000000" / "fringe" / "right_f1_s03.exr", "Y")
    assert np.abs(ours - np.clip(twin, 0, 1)).max() < 1e-4  # the twin's step 3, not image 3
    done = run_app("train", "adapt=true", f"init_from={base_run}", "root=mine",
                   "paths.output_dir=adapted", "adaptation.epochs=1", "adaptation.replay=0",
                   "trainer.enable_progress_bar=false", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert "test (no ground truth): MAE against the classical reconstruction " in done.stdout
    record = json.loads((tmp_path / "adapted" / "metrics.json").read_text())
    assert record["target"] == "classical" and record["calibration_check"] == "classical"
    assert 0 < record["test/classical_mae_mm"] < 20 and 0.3 < record["test/covered"] <= 1
    done = run_app("view", "adapted", cwd=tmp_path)  # its page: the depth beside its target
    assert done.returncode == 0, done.stderr[-2000:]
    page = (tmp_path / "adapted" / "page.html").read_text()
    assert "classical reconstruction (its target)" in page and "no run here kept" not in page
    assert "MAE against the classical reconstruction" in page
    ckpt = tmp_path / "adapted" / record["best_checkpoint"]
    done = run_app("predict", f"ckpt_path={ckpt}", "input=mine/scenes/000005", "out=pred",
                   cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert np.isfinite(read_channel(tmp_path / "pred" / "depth.exr", "Z")).mean() > 0.5
    # captures of the 1920 and 30 px fringes only: the net's 240 px image is not among them
    _captured(labelled, tmp_path / "other", (0, 2))
    done = run_app("convert", "format=sequences", "src=other", "manifest=mine",
                   "psp.periods=[1,64]", "out=theirs", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    done = run_app("train", "adapt=true", f"init_from={base_run}", "root=theirs",
                   "paths.output_dir=refused", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 2 and not (tmp_path / "refused").exists()
    assert "holds the 1920, 30 px fringe(s)" in done.stderr
    assert "trained on the 240 px fringe at step 0 of 12" in done.stderr
