"""A round body's frames, each moved across its axis onto the model's (annotate/tracking/axis_centring.py): a
procedural mug seen from many sides with depth noise, its frames off by a known offset in the object frame."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from annotate.tracking.axis_centring import Body, fit_body, frame_offset, shifted_onto_axis, wall_normals
from annotate.tracking.tilt import windowed_medians
from evaluate.geometry import transform, untransform
from sequences.synth.shapes import procedural_mesh

RADIUS, BAND, CLEAR, MIN_POINTS, VIEW = 0.016, 0.006, 40.0, 50, 60.0


def _mug(seed: int = 0) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A procedural mug (centred on its tight box, handle along -z) and its body's axis point (3,) at y = 0: the
    body's far side (+z) lies one radius (its x extent) beyond the axis."""
    mesh = procedural_mesh("mug", np.random.default_rng(seed))
    top = mesh.bounds[1]
    return mesh, np.array([0.0, 0.0, top[2] - top[0]])


def _seen(mesh: trimesh.Trimesh, camera: np.ndarray, seed: int, noise: float = 0.0015, voxel: float = 0.004) -> np.ndarray:
    """Points (object frame, m) of ``mesh`` facing a camera at ``camera`` (object frame), with Gaussian depth noise
    of ``noise`` m along each point's ray, one per ``voxel`` as the frame store keeps them."""
    rng = np.random.default_rng(seed)
    points, faces = trimesh.sample.sample_surface(mesh, 40000, seed=seed)
    rays = points - camera
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    facing = np.sum(mesh.face_normals[faces] * rays, axis=1) < 0
    points = points[facing] + rng.normal(0.0, noise, (int(facing.sum()), 1)) * rays[facing]
    _, first = np.unique(np.floor(points / voxel).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def _camera(azimuth_deg: float, elevation_deg: float, distance: float = 0.6) -> np.ndarray:
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    return distance * np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])


def _body(mesh: trimesh.Trimesh) -> Body:
    points, faces = trimesh.sample.sample_surface(mesh, 20000, seed=1)
    body = fit_body(points, mesh.face_normals[faces])
    assert body is not None
    return body


def test_the_models_body_gives_its_axis_radius_and_handle():
    mesh, axis = _mug()
    body = _body(mesh)
    np.testing.assert_allclose(body.point[[0, 2]], axis[[0, 2]], atol=2e-4)
    # the median distance from the axis of the points facing across it: the outer and inner walls (and the taper)
    assert mesh.bounds[1][0] - 0.008 < body.radius < mesh.bounds[1][0]
    np.testing.assert_allclose(body.handle, [0.0, 0.0, -1.0], atol=0.05)


@pytest.mark.parametrize("offset_mm", [(1.5, 0.0, -2.0), (-2.5, 0.0, 1.0)])
def test_a_frame_off_across_the_axis_measures_its_own_offset(offset_mm):
    # the frame's pose is off: its points lie shifted by ``offset`` in the object frame, and so does the axis they put
    mesh, _ = _mug()
    body = _body(mesh)
    offset = np.array(offset_mm) / 1000
    height = float(mesh.extents[1])
    measured = []
    for k, azimuth in enumerate(range(0, 360, 30)):
        camera = _camera(azimuth, 30.0)
        points = _seen(mesh, camera, seed=k) + offset
        found = frame_offset(points, camera + offset, body, RADIUS, BAND, CLEAR, height, MIN_POINTS, VIEW)
        assert found is not None, azimuth
        measured.append(found)
    measured = np.array(measured)
    assert np.all(measured[:, 1] == 0.0)  # square to the axis only
    # one frame alone: within 0.5 mm of the offset (measured 0.47); their median (the window's): within 0.14 mm
    assert np.abs(measured - offset).max() < 0.8e-3
    np.testing.assert_allclose(np.median(measured, axis=0), offset, atol=2e-4)


def test_grazing_normals_lean_towards_the_camera_and_are_left_out():
    # the normals of the wall seen nearly edge-on tilt towards the camera (depth noise along rays that run along the
    # surface): their normal lines meet nearer the camera than the axis, a lean the view limit leaves out
    mesh, _ = _mug()
    body = _body(mesh)
    height = float(mesh.extents[1])
    lean = {}
    for view_deg in (60.0, 90.0):
        along = []
        for k, azimuth in enumerate(range(0, 360, 30)):
            camera = _camera(azimuth, 20.0)
            found = frame_offset(_seen(mesh, camera, seed=k), camera, body, RADIUS, BAND, CLEAR, height, MIN_POINTS, view_deg)
            towards = (camera - body.point)[[0, 2]]
            along.append(found[[0, 2]] @ towards / np.linalg.norm(towards))
        lean[view_deg] = float(np.median(along))
    assert lean[90.0] > 0.7e-3  # measured 1.13 mm (0.74-2.0 in single frames); in the v5 mugs' runs 0.8-1.6 mm
    assert abs(lean[60.0]) < 0.2e-3  # measured -0.02 mm


def test_too_few_wall_points_measure_nothing():
    mesh, _ = _mug()
    body = _body(mesh)
    height = float(mesh.extents[1])
    camera = _camera(0.0, 85.0)  # from straight above: the rim and the inner bottom, little of the wall
    top = _seen(mesh, camera, seed=0)
    assert frame_offset(top, camera, body, RADIUS, BAND, CLEAR, height, 400, VIEW) is None
    assert frame_offset(top[:30], camera, body, RADIUS, BAND, CLEAR, height, MIN_POINTS, VIEW) is None
    assert fit_body(np.zeros((10, 3)), np.tile([1.0, 0.0, 0.0], (10, 1))) is None


def test_each_frame_takes_the_median_of_the_offsets_measured_near_it():
    ids = [f"{i:07d}" for i in range(7)]
    offsets = {ids[0]: np.array([1.0, 0, 0]), ids[1]: np.array([2.0, 0, 0]), ids[2]: np.array([9.0, 0, 0]), ids[5]: np.array([4.0, 0, 1])}
    window = windowed_medians(ids, offsets, 1, 2)
    np.testing.assert_allclose(window[ids[0]], [1.5, 0, 0])
    np.testing.assert_allclose(window[ids[1]], [2.0, 0, 0])  # the median of 1, 2 and 9
    np.testing.assert_allclose(window[ids[2]], [5.5, 0, 0])
    assert ids[4] not in window and ids[6] not in window  # one measured within one frame: fewer than two


def test_the_shift_moves_the_frames_points_by_the_offset_in_the_object_frame():
    rng = np.random.default_rng(3)
    pose = np.eye(4)
    pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * np.array([1, 1, 1])
    if np.linalg.det(pose[:3, :3]) < 0:
        pose[:3, 0] *= -1
    pose[:3, 3] = [0.1, -0.05, 0.7]
    seen = transform(pose, rng.normal(0, 0.05, (20, 3)))  # camera-frame points
    offset = np.array([0.002, 0.0, -0.001])
    np.testing.assert_allclose(untransform(shifted_onto_axis(pose, offset), seen), untransform(pose, seen) - offset, atol=1e-12)


def test_normals_face_the_camera():
    mesh, _ = _mug()
    camera = _camera(45.0, 30.0)
    points = _seen(mesh, camera, seed=0, noise=0.0)
    normals = wall_normals(points, RADIUS, camera)
    assert np.all(np.sum(normals * (camera - points), axis=1) > 0)
