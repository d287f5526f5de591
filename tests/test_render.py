"""Physics of the digital twin: exact depth, exact shadows, phase and triangulation closure."""

import dataclasses
import math

import numpy as np
import pytest
from helpers import CLEAN, FRINGE, RIG, render

from odmv.classical.fringe import triangulate_depth, unwrap_temporal, wrapped_phase
from odmv.data.augment import NEXT
from odmv.io.manifest import fringe_name
from odmv.rig import VIEW_NAMES
from odmv.sim.render import RenderConfig, render_scene
from odmv.sim.scenes import Scene, build_scene, draw_spec


def _plane_hits(size, normal, point):
    """Analytic intersection of every pixel-centre ray with a plane."""
    cam = RIG.camera_at(size)
    jj, ii = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    origin, d = cam.pixel_rays(np.stack([jj, ii], -1))
    t = ((point - origin) @ normal) / (d @ normal)
    return cam, origin + t[..., None] * d


def test_flat_ground_depth_and_frustum():
    r = render([], 96)
    cam, pts = _plane_hits(96, np.array([0.0, 0, 1]), np.zeros(3))
    assert np.abs(r.depth_mm - cam.depth(pts)).max() < 1e-3
    for name, proj in RIG.projectors().items():
        uv = proj.project(pts)
        w, h = proj.width_px, proj.height_px
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
        clear = (np.minimum(np.abs(uv[..., 0]), np.abs(uv[..., 0] - w)) > 0.01) & (
            np.minimum(np.abs(uv[..., 1]), np.abs(uv[..., 1] - h)) > 0.01
        )
        assert inside.any() and (~inside).any()  # the paper's 23 mm projector field is narrower
        assert np.array_equal(r.lit[name][clear], inside[clear]), name
        np.testing.assert_allclose(r.projector_coord[name][inside], uv[..., 0][inside], atol=2e-3)
        assert np.isnan(r.projector_coord[name][~inside]).all()


def test_tilted_plane_depth_is_analytic():
    tilt = 12.0
    slab = {
        "shape": "box",
        "size": [150, 150, 1.0],
        "position": [0, 0, 6.0],
        "rotation_deg": [tilt, 0, 0],
        "albedo": 0.7,
    }
    r = render([slab], 96)
    a = math.radians(tilt)
    normal = np.array([0, -math.sin(a), math.cos(a)])
    cam, pts = _plane_hits(96, normal, np.array([0, 0, 6.0]) + 0.5 * normal)
    assert np.abs(r.depth_mm - cam.depth(pts)).max() < 1e-3


AZIMUTH = {"right": (1, 0), "down": (0, -1), "left": (-1, 0), "up": (0, 1)}


@pytest.mark.parametrize("view", VIEW_NAMES)
def test_box_shadow_length_and_side(view):
    """A 3 mm box whose shadow-casting edge sits on the projector's optical axis (so the ray
    over it falls at exactly 26 deg) throws a shadow of h tan 26 deg on the far side only."""
    h, half, size = 3.0, 0.25, 480
    ax, ay = AZIMUTH[view]
    offset = h * math.tan(math.radians(26)) + half  # box centre along the baseline
    box = {
        "shape": "box",
        "size": [2 * half, 2 * half, h],
        "albedo": 0.8,
        "position": [ax * offset, ay * offset, h / 2],
    }
    r = render([box], size)
    px_mm = 35.47 / size
    expected_px = h * math.tan(math.radians(26)) / px_mm
    ground = np.abs(r.depth_mm - 150.0) < 1e-3
    cam = RIG.camera_at(size)
    bu, bv = cam.project(np.array(box["position"]) * [1, 1, 0], distorted=False).astype(int)

    def outward(img, towards_projector):
        """Pixels from the box outwards along the baseline, away from / towards the projector."""
        img_dir = (ax, -ay)  # world +y is image up
        line = img[bv, :] if ax else img[:, bu]
        start = bu if ax else bv
        sign = (img_dir[0] or img_dir[1]) * (1 if towards_projector else -1)
        return line[start:] if sign > 0 else line[start::-1]

    for towards, want in ((False, expected_px), (True, 0.0)):
        first_ground = int(np.argmax(outward(ground, towards)))
        lit = outward(r.lit[view], towards)[first_ground:]
        dark_px = int(np.argmax(lit))  # unlit ground pixels before the first lit one
        assert abs(dark_px - want) <= 1.0, (towards, dark_px, want)


@pytest.fixture(scope="module")
def full_render():
    parts = [
        {"shape": "box", "size": [6, 5, 4], "position": [3, -2, 2], "albedo": 0.8},
        {"shape": "sphere", "size": [3.0], "position": [-6, 5, 1.5], "albedo": 0.6},
        {"shape": "cylinder", "size": [2, 6], "position": [-5, -6, 3], "albedo": 0.7},
    ]
    return render(parts, 128, images="full")


def _interior(lit, depth):
    """Lit pixels whose 3x3 neighbourhood is lit and free of depth edges."""
    from numpy.lib.stride_tricks import sliding_window_view as windows

    l3 = windows(np.pad(lit, 1), (3, 3)).all((-1, -2))
    d3 = np.ptp(windows(np.pad(depth, 1, mode="edge"), (3, 3)), axis=(-1, -2))
    return l3 & (d3 < 0.2)


def _phases(r, view):
    return [
        wrapped_phase(np.stack([r.fringes[fringe_name(view, f, n)] for n in range(12)]))[0]
        for f in range(len(FRINGE.periods_px))
    ]


@pytest.mark.parametrize("view", VIEW_NAMES)
def test_phase_matches_ground_truth_projector_coordinate(full_render, view):
    r = full_render
    assert len(r.fringes) == 4 * 37
    phase = _phases(r, view)[-1]
    truth = np.mod(2 * np.pi * r.projector_coord[view] / FRINGE.periods_px[-1], 2 * np.pi)
    err = np.abs(np.angle(np.exp(1j * (phase - truth))))
    inner = _interior(r.lit[view], r.depth_mm)
    assert inner.mean() > 0.3
    assert np.median(err[inner]) < 1e-3 and np.percentile(err[inner], 99) < 5e-3


@pytest.mark.parametrize("view", VIEW_NAMES)
def test_unwrapped_phase_triangulates_to_ground_truth_depth(full_render, view):
    r = full_render
    u = unwrap_temporal(_phases(r, view), list(FRINGE.periods_px))
    depth = triangulate_depth(u, RIG.camera_at(128), RIG.projectors()[view])
    lit = r.lit[view]
    err = np.abs(depth - r.depth_mm)[lit]
    assert np.median(err) < 0.01
    assert np.percentile(err, 90) < 0.01


def test_noise_gamma_and_defocus_change_images_as_expected():
    parts = [{"shape": "box", "size": [6, 5, 4], "position": [3, -2, 2], "albedo": 0.8}]
    clean = render(parts, 64, images="full")
    noisy = render(parts, 64, images="full", cfg=RenderConfig())
    key = fringe_name("right", 2, 0)
    diff = noisy.fringes[key] - clean.fringes[key]
    assert 0.002 < diff.std() < 0.02  # Poisson-Gaussian at ~20k e- full well
    blurred = render(
        parts,
        64,
        images="full",
        cfg=RenderConfig(full_well_e=0, read_noise=0, defocus_sigma_px=1.5),
    )
    fine = np.abs(np.diff(clean.fringes[key], axis=1)).mean()
    assert np.abs(np.diff(blurred.fringes[key], axis=1)).mean() < 0.8 * fine
    gamma = render(
        parts, 64, images="full", cfg=RenderConfig(full_well_e=0, read_noise=0, projector_gamma=2.2)
    )
    phase_clean = _phases(clean, "right")[-1]
    phase_gamma = _phases(gamma, "right")[-1]
    lit = clean.lit["right"]
    # 12 steps cancel the harmonics of a gamma curve up to order 11: phase barely moves
    assert np.median(np.abs(np.angle(np.exp(1j * (phase_gamma - phase_clean))))[lit]) < 1e-3
    assert not np.allclose(gamma.fringes[key], clean.fringes[key])
    for img in list(noisy.fringes.values()) + list(gamma.fringes.values()):
        assert img.dtype == np.float32 and img.min() >= 0 and img.max() <= 1.0


def test_a_quarter_turn_of_the_scene_turns_the_images_and_hands_each_view_on():
    # the rig's symmetry behind data.augment=rot90: exact without the lens's tangential terms
    k1, k2, _, _ = RIG.camera.distortion
    rig = dataclasses.replace(
        RIG, camera=dataclasses.replace(RIG.camera, distortion=(k1, k2, 0, 0))
    )
    scene = build_scene(draw_spec("pcb", np.random.default_rng(3)))
    turn = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # +90 degrees about the camera axis
    turned = Scene(scene.triangles @ turn.T, scene.albedo)
    a, b = (
        render_scene(s, rig, 48, 48, FRINGE, VIEW_NAMES, CLEAN, np.random.default_rng(0))
        for s in (scene, turned)
    )
    np.testing.assert_allclose(b.depth_mm, np.rot90(a.depth_mm), atol=1e-4)
    for v in VIEW_NAMES:
        assert np.array_equal(b.lit[NEXT[v]], np.rot90(a.lit[v]))
    assert len(a.fringes) == 4 * (3 * 12 + 1)  # every sequence and the uniform image
    for name, image in a.fringes.items():  # "<view>_f<frequency>_s<step>.exr", "<view>_uniform.exr"
        view, rest = name.split("_", 1)
        np.testing.assert_allclose(b.fringes[f"{NEXT[view]}_{rest}"], np.rot90(image), atol=1e-4)
    assert a.lit["right"].mean() != a.lit["up"].mean()  # the views differ: the test can fail
