"""The classical decoder on phase-shifting sequences as real rigs save them: other shift
directions, other first phases, other file numbering, 8-bit PNG; and the wrong conventions
named, not decoded into a silently wrong phase."""

import json

import numpy as np
import pytest
from helpers import FRINGE, RIG, compose_config, render
from PIL import Image as PILImage

from odmv.classical import fringe as fpp
from odmv.classical.sequences import PspOptions, SequenceError
from odmv.deploy.predict import predict
from odmv.io.calibration import calibration_of
from odmv.io.exr import read_exr
from odmv.io.manifest import fringe_name

STEPS = FRINGE.steps
PERIODS = [RIG.projectors()["right"].width_px / p for p in FRINGE.periods_px]  # 1, 8, 64


@pytest.fixture(scope="module")
def twin():
    parts = [
        {"shape": "box", "size": [6, 5, 4], "position": [3, -2, 2], "albedo": 0.8},
        {"shape": "sphere", "size": [3.0], "position": [-6, 5, 1.5], "albedo": 0.6},
    ]
    return render(parts, 128, images="full")


def write_sequences(
    r, folder, views, shift_sign, origin_steps, pattern, first_index, frequencies=(0, 1, 2)
):
    """The twin's sequences re-ordered into another convention, as 8-bit PNG: image n of a
    frequency is A + B cos(phi + shift_sign 2 pi n / N + 2 pi origin_steps / N), which is the
    twin's image (shift_sign n + origin_steps) mod N."""
    options = PspOptions(pattern=pattern, first_index=first_index)
    for view in views:
        for f, source in enumerate(frequencies):
            for n in range(STEPS):
                step = (shift_sign * n + origin_steps) % STEPS
                twin = r.fringes[fringe_name(view, source, step)]
                path = folder / f"{options.stem(view, f, n, STEPS)}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                level = np.round(np.clip(twin, 0, 1) * 255).astype(np.uint8)
                PILImage.fromarray(level).save(path)


def decode(folder, out, *options):
    cfg = compose_config(
        "predict", ["method=psp", f"input={folder}", f"out={out}", "psp.periods=[1,8,64]", *options]
    )
    return predict(cfg)


@pytest.mark.parametrize(
    "shift_sign, origin_steps, pattern, first_index",
    [
        (1, 0, "{view}_f{f}_s{s:02d}", 0),  # the twin's own
        (-1, 0, "{view}/{n}", 1),  # shifted the other way, numbered 1..36 in one folder per view
        (1, STEPS // 2, "img_{view}_{f}_{s}", 1),  # the first image at phase pi
    ],
)
def test_each_convention_decodes_to_the_projector_coordinate(
    twin, tmp_path, shift_sign, origin_steps, pattern, first_index
):
    views = ["right", "up"]
    write_sequences(twin, tmp_path / "in", views, shift_sign, origin_steps, pattern, first_index)
    origin = 2 * np.pi * origin_steps / STEPS
    extra = ["psp.steps=12"] if "{n" in pattern else []
    (done,) = decode(
        tmp_path / "in",
        tmp_path / "out",
        f"psp.shift_sign={shift_sign}",
        f"psp.phase_origin_rad={origin!r}",
        f"psp.pattern='{pattern}'",
        f"psp.first_index={first_index}",
        *extra,
    )
    assert "depth" not in done  # no calibration: the phase only
    for view in views:
        phase = np.load(tmp_path / "out" / f"{view}_phase.npy")
        assert (tmp_path / "out" / f"{view}_modulation.exr").is_file()
        coord_px = phase / (2 * np.pi) * FRINGE.periods_px[-1]
        lit = twin.lit[view] & np.isfinite(twin.projector_coord[view])
        kept = lit & np.isfinite(coord_px)
        assert kept.sum() > 0.8 * lit.sum()
        err = np.abs(coord_px - twin.projector_coord[view])[kept]
        assert np.median(err) < 0.05 and np.percentile(err, 95) < 0.05, (view, np.median(err))


def test_a_wrong_phase_origin_is_named_with_the_fix(twin, tmp_path):
    write_sequences(twin, tmp_path / "in", ["left"], 1, STEPS // 2, "{view}_f{f}_s{s:02d}", 0)
    with pytest.raises(SequenceError, match=r"left: .* only .* psp.phase_origin_rad=3.14159"):
        decode(tmp_path / "in", tmp_path / "out")
    # a shift the other way is self-consistent: read with the wrong sign it decodes, without
    # complaint, to the mirrored coordinate (so only a calibration can tell it)
    write_sequences(twin, tmp_path / "rev", ["left"], -1, 0, "{view}_f{f}_s{s:02d}", 0)
    decode(tmp_path / "rev", tmp_path / "right_way", "psp.shift_sign=-1")
    decode(tmp_path / "rev", tmp_path / "wrong_way")
    right = np.load(tmp_path / "right_way" / "left_phase.npy")
    wrong = np.load(tmp_path / "wrong_way" / "left_phase.npy")
    both = np.isfinite(right) & np.isfinite(wrong)
    assert both.mean() > 0.3
    np.testing.assert_allclose(wrong[both], 2 * np.pi * PERIODS[-1] - right[both], atol=1e-3)


def test_spatial_unwrapping_is_right_up_to_whole_coarse_periods(twin, tmp_path):
    """Without a one-period sequence (8 and 64 periods only), psp.unwrap=spatial unwraps the
    coarser one over each connected region: off by a whole number of its periods."""
    write_sequences(twin, tmp_path / "in", ["down"], 1, 0, "{view}_f{f}_s{s:02d}", 0, (1, 2))
    cfg = compose_config(
        "predict",
        [
            "method=psp",
            f"input={tmp_path / 'in'}",
            f"out={tmp_path / 'out'}",
            "psp.periods=[8,64]",
            "psp.unwrap=spatial",
        ],
    )
    predict(cfg)
    phase = np.load(tmp_path / "out" / "down_phase.npy")
    truth = 2 * np.pi * twin.projector_coord["down"] / FRINGE.periods_px[-1]
    both = np.isfinite(phase) & twin.lit["down"]
    assert both.mean() > 0.4
    periods_off = (truth - phase)[both] / (2 * np.pi * 8)  # in coarse periods
    whole = np.round(periods_off)
    assert np.percentile(np.abs(periods_off - whole), 99) < 0.01
    assert np.mean(whole == np.median(whole)) > 0.9  # one offset for the big region


def test_depth_with_a_calibration_matches_the_twin(twin, tmp_path, monkeypatch):
    """With the rig's calibration the same sequences give depth (mm) where the views agree, and
    each view is decoded once, from the sequences the camera resolves (at 128 px the 64-period
    one aliases: 2.5 camera px a period), for its phase file and its depth alike."""
    sequences_read = []
    wrapped = fpp.wrapped_phase
    monkeypatch.setattr(
        fpp, "wrapped_phase", lambda *a, **k: sequences_read.append(1) or wrapped(*a, **k)
    )
    write_sequences(twin, tmp_path / "in", ["right", "left"], -1, 3, "{view}_f{f}_s{s:02d}", 0)
    (tmp_path / "rig.json").write_text(json.dumps(calibration_of(RIG, 128, 128)))
    (done,) = decode(
        tmp_path / "in",
        tmp_path / "out",
        f"calibration={tmp_path / 'rig.json'}",
        "psp.shift_sign=-1",
        f"psp.phase_origin_rad={2 * np.pi * 3 / STEPS!r}",
    )
    depth = read_exr(done["depth"])["Z"]
    ok = np.isfinite(depth)
    assert ok.mean() > 0.5
    assert np.abs(depth - twin.depth_mm)[ok].mean() < 0.02
    # per view: the two coarsest sequences for the conventions' check, then the two resolved
    assert len(sequences_read) == 2 * (2 + 2)
    for view in ("right", "left"):
        phase = np.load(tmp_path / "out" / f"{view}_phase.npy")
        coord_px = phase / (2 * np.pi) * FRINGE.periods_px[-1]
        kept = np.isfinite(coord_px) & twin.lit[view] & np.isfinite(twin.projector_coord[view])
        assert kept.sum() > 0.8 * twin.lit[view].sum()
        # to 0.1 px (0.06 measured), the 8-period sequence's precision: the 64-period one that
        # gives 0.05 px without a calibration is not used
        assert np.median(np.abs(coord_px - twin.projector_coord[view])[kept]) < 0.1


def test_bad_options_are_named():
    with pytest.raises(ValueError, match="psp.periods: the coarsest frequency has 4 periods"):
        PspOptions.from_cfg({"periods": [4, 16]})
    with pytest.raises(ValueError, match="psp.shift_sign: 2"):
        PspOptions.from_cfg({"shift_sign": 2})
    with pytest.raises(ValueError, match="psp.pattern"):
        PspOptions.from_cfg({"pattern": "{camera}_{s}"})
    with pytest.raises(ValueError, match="psp.colour: unknown"):
        PspOptions.from_cfg({"colour": 1})
