"""Shifts of the twin (odmv.sim.shifts): each perturbation is applied as stated, and at its
nominal strength renders the nominal images byte for byte."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from helpers import CLEAN, FRINGE, RIG

from odmv.io.exr import read_exr
from odmv.io.manifest import FRINGE_CHANNEL, FRINGE_DIR, fringe_name, load_manifest, uniform_name
from odmv.rig import VIEW_NAMES
from odmv.sim.render import GLOSS_EXPONENT, specular
from odmv.sim.scenes import build_scene
from odmv.sim.shifts import NOMINAL, Shift, ShiftError, parse_shift
from odmv.sim.writer import SimSettings, _render, rerender, simulate

BOX = {"shape": "box", "size": [6, 5, 3], "position": [1, -1, 1.5], "rotation_deg": [0, 0, 20],
       "albedo": 0.8}  # fmt: skip
SCENE = build_scene({"parts": [BOX]})
NOISY = replace(CLEAN, full_well_e=20000.0, read_noise=0.002)  # the nominal sensor


def _render_with(shift, size=32, cfg=CLEAN, images="full", ss=None, rig=RIG):
    cfg = cfg if ss is None else replace(cfg, supersample=ss)
    return _render(
        SCENE, rig, size, size, FRINGE, VIEW_NAMES, cfg, shift, np.random.default_rng(7), images
    )


@pytest.mark.parametrize("name", [n for n in NOMINAL if n != "none"])
def test_every_shift_at_its_nominal_strength_renders_the_nominal_images(name):
    plain = _render_with(Shift(), cfg=NOISY)
    shifted = _render_with(Shift(name, NOMINAL[name]), cfg=NOISY)
    assert shifted.fringes.keys() == plain.fringes.keys()
    for key, img in plain.fringes.items():
        assert img.tobytes() == shifted.fringes[key].tobytes(), key
    assert plain.depth_mm.tobytes() == shifted.depth_mm.tobytes()


def test_gamma_maps_the_pattern_through_the_power():
    # one ray per pixel, no noise, no ambient: a fringe over the white image is the pattern
    # (A + B cos)^gamma / (A + B)^gamma, so gamma X raises the linear projector's ratio to X
    cfg = replace(CLEAN, ambient=0.0)
    linear = _render_with(Shift(), cfg=cfg, ss=1)
    gamma = _render_with(Shift("gamma", 2.2), cfg=cfg, ss=1)
    for v in VIEW_NAMES:
        lit = linear.lit[v] & (linear.fringes[uniform_name(v)] > 0.05)
        assert lit.sum() > 50
        f = fringe_name(v, 2, 0)
        r1 = linear.fringes[f][lit] / linear.fringes[uniform_name(v)][lit]
        rg = gamma.fringes[f][lit] / gamma.fringes[uniform_name(v)][lit]
        np.testing.assert_allclose(rg, r1**2.2, atol=0.01)
        assert np.abs(rg - r1).max() > 0.1  # and the change is not small


def test_defocus_lowers_the_images_high_spatial_frequencies():
    sharp = _render_with(Shift(), size=64)
    blurred = _render_with(Shift("defocus", 1.5), size=64)
    key = fringe_name("right", 2, 0)

    def power(img, lo, hi):  # spectral power at radial frequencies lo..hi (cycles/px)
        spec = np.abs(np.fft.fft2(img - img.mean())) ** 2
        fy, fx = np.meshgrid(np.fft.fftfreq(64), np.fft.fftfreq(64), indexing="ij")
        band = (np.hypot(fx, fy) >= lo) & (np.hypot(fx, fy) < hi)
        return spec[band].sum()

    low = power(blurred.fringes[key], 0.02, 0.08) / power(sharp.fringes[key], 0.02, 0.08)
    high = power(blurred.fringes[key], 0.25, 0.5) / power(sharp.fringes[key], 0.25, 0.5)
    # a Gaussian of sigma 1.5 px passes exp(-2 pi^2 sigma^2 f^2) in amplitude: about 0.9 at
    # 0.05 cycles/px and 0.06 at 0.25 (power 0.004; the image's borders, reflected, add some)
    assert low > 0.5 and high < 0.05 and high < low / 20


def test_a_turned_projector_renders_phase_the_nominal_calibration_does_not_predict():
    turned = Shift("projector_rotation", 0.5, seed=3)
    r = _render_with(turned, size=48)
    nominal, actual = RIG.projectors(), turned.rig(RIG).projectors()
    cam = RIG.camera_at(48)
    for v in VIEW_NAMES:
        # the centre stays, the pose turns by 0.5 degrees
        np.testing.assert_allclose(actual[v].center, nominal[v].center, atol=1e-9)
        cos = (np.trace(actual[v].R @ nominal[v].R.T) - 1) / 2
        assert math.degrees(math.acos(min(1.0, cos))) == pytest.approx(0.5, abs=1e-6)
    # the ground truth projector columns come from the turned projector; on the ground plane,
    # where the nominal reference phase is computed, they miss the nominal ones by pixels
    jj, ii = np.meshgrid(np.arange(48) + 0.5, np.arange(48) + 0.5)
    origin, d = cam.pixel_rays(np.stack([jj, ii], -1))
    ground = origin + (-origin[2] / d[..., 2])[..., None] * d
    on_ground = r.depth_mm > 149.99
    moved = []
    for v in VIEW_NAMES:
        ok = on_ground & np.isfinite(r.projector_coord[v])
        np.testing.assert_allclose(
            r.projector_coord[v][ok], actual[v].project(ground)[..., 0][ok], atol=5e-3
        )
        moved.append(np.abs(r.projector_coord[v][ok] - nominal[v].project(ground)[..., 0][ok]))
    assert np.mean(np.concatenate(moved)) > 5  # px of 1920: 0.5 deg at 167 mm is ~70 px at most
    # and the draws are the seed's: another seed turns the projectors about other axes
    other = Shift("projector_rotation", 0.5, seed=4).rig(RIG).projectors()
    assert not np.allclose(other["right"].R, actual["right"].R)


def test_a_moved_projector_and_a_longer_focal_length():
    moved = Shift("projector_shift", 2.0, seed=1).rig(RIG).projectors()
    for v, p in RIG.projectors().items():
        assert np.linalg.norm(moved[v].center - p.center) == pytest.approx(2.0)
        np.testing.assert_allclose(moved[v].R, p.R)
    longer = Shift("camera_focal", 2.0).rig(RIG)
    assert longer.camera.focal_mm == pytest.approx(RIG.camera.focal_mm * 1.02)
    assert longer.camera_at(32).K[0, 0] == pytest.approx(RIG.camera_at(32).K[0, 0] * 1.02)


def test_a_dead_projector_leaves_its_view_at_ambient_level():
    r = _render_with(Shift("dead_view", "down"))
    nominal = _render_with(Shift())
    # ambient light alone: the ambient irradiance times the surface's albedo
    ambient = _render_with(Shift(), cfg=replace(CLEAN, projector_irradiance=0.0))
    for key, img in r.fringes.items():
        if key.startswith("down"):
            np.testing.assert_array_equal(img, ambient.fringes[key])
            assert img.max() <= CLEAN.ambient * 0.8 + 1e-6  # the brightest albedo, 0.8
        else:
            np.testing.assert_array_equal(img, nominal.fringes[key])
    for v in VIEW_NAMES:  # the ground truth is the rig's geometry, which did not change
        np.testing.assert_array_equal(r.lit[v], nominal.lit[v])


def test_gloss_is_a_lobe_about_the_mirror_direction():
    # the lobe alone: a surface point, its normal up, the camera above and a projector placed
    # where the camera's mirror image looks: the peak; turned away, the lobe falls as
    # cos(angle / 2)^GLOSS_EXPONENT (the half vector turns by half the angle)
    point, normal = np.zeros((1, 3)), np.array([[0.0, 0, 1]])
    camera = np.array([-50.0, 0, 100.0])
    lit = np.array([True])
    for turn_deg in (0, 10, 40):
        a = math.radians(math.degrees(math.atan2(50, 100)) + turn_deg)
        projector = 111.8 * np.array([math.sin(a), 0, math.cos(a)])
        lobe = specular(point, normal, lit, projector, camera, 111.8)[0]
        assert lobe == pytest.approx(math.cos(math.radians(turn_deg / 2)) ** GLOSS_EXPONENT)
    assert specular(point, normal, ~lit, projector, camera, 111.8)[0] == 0  # unlit: none
    # rendered: gloss only adds light, nowhere outside the projector's light, most where the
    # lobe peaks, and highlights saturate
    plain = _render_with(Shift(), ss=1)
    glossy = _render_with(Shift("gloss", 3.0), ss=1)
    for v in VIEW_NAMES:
        added = glossy.fringes[uniform_name(v)] - plain.fringes[uniform_name(v)]
        assert added.min() >= -1e-6 and added.max() > 0.05
        assert np.all(added[~plain.lit[v]] <= 1e-6)
    assert max(img.max() for img in glossy.fringes.values()) == 1.0


def test_texture_marks_the_parts_albedo_and_not_the_ground():
    plain = _render_with(Shift(), ss=1, cfg=replace(CLEAN, ambient=0.0))
    printed = _render_with(Shift("texture", 0.6), ss=1, cfg=replace(CLEAN, ambient=0.0))
    white = uniform_name("right")
    lit = plain.lit["right"] & (plain.fringes[white] > 0.01)
    ratio = printed.fringes[white][lit] / plain.fringes[white][lit]
    on_part = (plain.depth_mm < 149.9)[lit]
    assert np.allclose(ratio[~on_part], 1.0)  # the ground keeps its albedo
    marked = np.isclose(ratio[on_part], 0.4, atol=1e-4)
    assert np.all(marked | np.isclose(ratio[on_part], 1.0, atol=1e-4))
    assert 0.15 < marked.mean() < 0.6  # a third of the grid's cells, sharp-edged


def test_exposure_and_noise_scale_as_stated():
    bright = _render_with(Shift("exposure", 3.0))
    plain = _render_with(Shift())
    key = fringe_name("up", 2, 0)
    dim = plain.fringes[key] < 0.3
    np.testing.assert_allclose(bright.fringes[key][dim], 3 * plain.fringes[key][dim], rtol=1e-5)
    assert bright.fringes[key].max() == 1.0  # saturated above full scale
    residual = {}
    for x in (1.0, 4.0):
        noisy = _render_with(Shift("noise", x), cfg=NOISY)
        residual[x] = np.std(noisy.fringes[key] - plain.fringes[key])
    assert residual[4.0] / residual[1.0] == pytest.approx(4.0, rel=0.15)


def test_bad_shifts_are_named_in_one_line():
    for bad, match in (
        (lambda: Shift("wobble", 1), "wobble.*unknown"),
        (lambda: Shift("gamma", "lots"), "gamma: strength 'lots' is not a number"),
        (lambda: Shift("gamma", 0), "out of range"),
        (lambda: Shift("defocus", -1), "must not be negative"),
        (lambda: Shift("dead_view", "middle"), "'middle' is not a view"),
        (lambda: parse_shift("noise:x"), "not a number"),
    ):
        with pytest.raises(ShiftError, match=match) as e:
            bad()
        assert "\n" not in str(e.value)
    assert parse_shift("gamma:2.2") == Shift("gamma", 2.2)
    assert parse_shift("dead_view:up").label() == "dead_view:up"
    assert Shift("gamma", 1).nominal and Shift("gamma", 1).label() == "nominal"


def test_a_shifted_dataset_keeps_the_nominal_calibration_and_rerenders_exactly(tmp_path):
    shift = Shift("projector_rotation", 0.5, seed=2)
    s = SimSettings(out=tmp_path / "turned", scenes=2, height_px=32, width_px=32, shift=shift)
    simulate(s, workers=1, progress=False)
    m = load_manifest(s.out)
    assert m.rig == RIG  # what the user's calibration says
    assert m.extra["simulation"]["shift"] == shift.to_dict()
    nominal = SimSettings(out=tmp_path / "nominal", scenes=2, height_px=32, width_px=32)
    simulate(nominal, workers=1, progress=False)
    assert "shift" not in load_manifest(nominal.out).extra["simulation"]  # as before shifts
    _, again = rerender(s.out, "000000")
    _, plain = rerender(nominal.out, "000000")
    key = fringe_name("right", 2, 0)
    stored = read_exr(m.scene_dir("000000") / FRINGE_DIR / key)[FRINGE_CHANNEL]
    np.testing.assert_array_equal(stored, again.fringes[key])  # the files, read back
    assert not np.array_equal(again.fringes[key], plain.fringes[key])
    assert (
        json.loads((s.out / "manifest.json").read_text())["rig"]
        == json.loads((nominal.out / "manifest.json").read_text())["rig"]
    )


def test_domain_randomization_draws_each_training_scenes_shifts_and_keeps_the_others(tmp_path):
    profile = {"gamma": [1.2, 2.0], "projector_rotation": [0.0, 0.1], "texture": [0.2, 0.5]}
    kw = {"scenes": 10, "height_px": 32, "width_px": 32, "seed": 3}
    randomized = SimSettings(out=tmp_path / "dr", randomize=profile, **kw)
    nominal = SimSettings(out=tmp_path / "nominal", **kw)
    for s in (randomized, nominal):
        simulate(s, workers=1, progress=False)
    m = load_manifest(randomized.out)
    assert m.extra["simulation"]["randomize"] == profile and m.rig == RIG
    key = fringe_name("right", 2, 0)
    strengths = []
    for scene in m.scenes:
        stored = read_exr(m.scene_dir(scene["id"]) / FRINGE_DIR / key)[FRINGE_CHANNEL]
        plain = read_exr(nominal.out / "scenes" / scene["id"] / FRINGE_DIR / key)[FRINGE_CHANNEL]
        if scene["split"] != "train":  # validation and test stay the nominal twin
            assert "shifts" not in scene and np.array_equal(stored, plain)
            continue
        drawn = {d["name"]: d["strength"] for d in scene["shifts"]}
        assert drawn.keys() == profile.keys()
        assert all(lo <= drawn[k] <= hi for k, (lo, hi) in profile.items())
        strengths.append(drawn["gamma"])
        assert not np.array_equal(stored, plain)
        _, again = rerender(randomized.out, scene["id"])  # the record renders it again exactly
        np.testing.assert_array_equal(stored, again.fringes[key])
    assert len(set(strengths)) == len(strengths) >= 6  # each scene its own draw
    with pytest.raises(ValueError, match="randomize.dead_view"):
        SimSettings(out=tmp_path / "x", randomize={"dead_view": [0, 1]})
    with pytest.raises(ShiftError, match="gamma"):
        SimSettings(out=tmp_path / "x", randomize={"gamma": [0.0, 2.0]})


def test_data_randomize_names_a_profile_and_renders_its_own_dataset():
    from helpers import compose_config

    nominal = compose_config("train", ["experiment=mini"])
    randomized = compose_config("train", ["experiment=mini", "data.randomize=all"])
    assert randomized.data.simulate.randomize.gamma == [1.0, 2.2]
    assert nominal.data.root != randomized.data.root  # a dataset of its own
    assert nominal.data.root.endswith("synthetic-200x64px-4609dd24")  # today's, unchanged
    with pytest.raises(Exception, match="no such profile"):
        assert compose_config("train", ["data.randomize=bogus"]).data.root
