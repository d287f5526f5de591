import math

import numpy as np
import pytest

from odmv.rig import VIEW_NAMES, VIEW_SETS, CameraSpec, Rig, check_views


@pytest.fixture(scope="module")
def rig():
    return Rig()


def test_views_are_the_papers_order():
    assert VIEW_NAMES == ("right", "down", "left", "up")
    assert VIEW_SETS[3] == ("right", "left", "up")
    assert check_views(["up", "right"]) == ("right", "up")
    with pytest.raises(ValueError, match="unknown view"):
        check_views(["front"])


@pytest.mark.parametrize("name", VIEW_NAMES)
def test_projector_axis_meets_camera_axis_on_reference_plane_at_26_deg(rig, name):
    p = rig.projectors()[name]
    c, a = p.center, p.axis
    s = -c[2] / a[2]  # where the optical axis reaches z = 0
    np.testing.assert_allclose(c + s * a, [0, 0, 0], atol=1e-9)
    angle = math.degrees(math.acos(a @ np.array([0.0, 0.0, -1.0])))
    assert angle == pytest.approx(26.0, abs=1e-9)


def test_projectors_sit_on_their_named_side(rig):
    cam = rig.camera_at(480)
    for name, p in rig.projectors().items():
        u, v = cam.project(p.center[None] * np.array([1, 1, 0]), distorted=False)[0] - 240
        side = {
            "right": u > 0 and abs(v) < 1e-6,
            "left": u < 0 and abs(v) < 1e-6,
            "down": v > 0 and abs(u) < 1e-6,
            "up": v < 0 and abs(u) < 1e-6,
        }
        assert side[name], name


@pytest.mark.parametrize("name", VIEW_NAMES)
def test_project_then_back_project_gives_the_same_ray(rig, name):
    p = rig.projectors()[name]
    rng = np.random.default_rng(0)
    pts = rng.uniform([-15, -15, -2], [15, 15, 12], size=(50, 3))
    origin, d = p.rays(p.project(pts))
    to_pts = pts - origin
    along = (to_pts * d).sum(-1, keepdims=True)
    assert (along > 0).all()
    np.testing.assert_allclose(origin + along * d, pts, atol=1e-9)


@pytest.mark.parametrize("size", [480, 4800])
def test_camera_maps_field_corners_to_image_corners(rig, size):
    cam = rig.camera_at(size)
    half = 35.47 / 2
    corners = np.array([[-half, half, 0], [half, half, 0], [-half, -half, 0], [half, -half, 0.0]])
    uvw = np.c_[corners, np.ones(4)] @ cam.P.T
    uv = uvw[:, :2] / uvw[:, 2:]
    np.testing.assert_allclose(uv, [[0, 0], [size, 0], [0, size], [size, size]], atol=1e-9)
    np.testing.assert_allclose(cam.depth(corners), 150.0)


def test_distortion_round_trip_and_rays(rig):
    cam = rig.camera_at(480)
    rng = np.random.default_rng(1)
    uv = rng.uniform(0, 480, size=(100, 2))
    origin, d = cam.pixel_rays(uv)
    pts = origin + d * (150.0 / -d[:, 2:3])  # hit the reference plane
    np.testing.assert_allclose(cam.project(pts), uv, atol=1e-8)
    # distortion is small but real: about a pixel or less at the corner at 480 px
    shift = np.abs(cam.project(pts) - cam.project(pts, distorted=False)).max()
    assert 0.05 < shift < 2.0


def test_focal_length_override_changes_field():
    spec = CameraSpec(focal_length_mm=50.0)
    assert spec.field_at_reference_mm[0] == pytest.approx(15.36 * 150 / 50)
    assert CameraSpec().focal_mm == pytest.approx(150 * 15.36 / 35.47)


def test_rig_round_trips_through_dict(rig):
    again = Rig.from_dict(rig.to_dict())
    assert again == rig
    g = again.geometry(480)
    assert set(g["projectors"]) == set(VIEW_NAMES)
    assert g["projectors"]["right"]["phase_axis"] == "u"
