"""One definition of each convention: the tinted faces (3D box and 2D overlay alike), the symmetric categories,
back-projection, the sensor's depth noise."""

from __future__ import annotations

import numpy as np
import pytest
import viser
from PIL import Image, ImageDraw
from scipy.spatial.transform import Rotation

from annotate.app_scene import SceneView
from annotate.app_state import FACING_CAMERA
from annotate.app_views import TINT_OPACITY, TINTED_FACES, draw_box
from sequences.camera import Camera


def _tilted_pose() -> tuple[np.ndarray, np.ndarray]:
    """A box facing the camera (front, -z, towards it; up, +y, up in the image), its top tilted 30 deg towards the
    camera and turned 20 deg: both tinted faces in view, neither drawn over the other."""
    turn = Rotation.from_euler("xy", [30, 20], degrees=True)  # about camera axes
    return np.array([0.02, -0.01, 0.8]), (turn * Rotation.from_quat(FACING_CAMERA)).as_quat()


def test_the_3d_box_and_the_2d_overlay_tint_the_same_faces():
    camera = Camera()
    position, orientation = _tilted_pose()
    extents = np.array([0.16, 0.12, 0.10])
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        scene = SceneView(server, camera)
        scene.show_pose(position, orientation)
        scene.show_box(extents, own_pose=True)
        overlay = draw_box(np.zeros((camera.height, camera.width, 3), np.uint8), camera, position, orientation, extents, width=1, labels=False)
        R = Rotation.from_quat(np.roll(np.asarray(scene.gizmo.wxyz), -1)).as_matrix()  # the gizmo's pose: the 3D box's
        for face in TINTED_FACES:
            mesh = scene.tints[face.name]
            assert tuple(int(c) for c in mesh.color) == face.color and mesh.opacity == pytest.approx(TINT_OPACITY)
            vertices = np.asarray(mesh.vertices, dtype=np.float64)  # object frame, below the gizmo
            centre = vertices.mean(axis=0)
            assert np.sign(centre[face.axis]) == face.sign and np.abs(np.delete(centre, face.axis)).max() < 1e-6
            # the 3D face, seen by the camera: its projection rasterised
            points = vertices @ R.T + np.asarray(scene.gizmo.position)
            assert np.dot(R @ centre, points.mean(axis=0)) < 0, f"{face.name} should face the camera in this pose"
            uv, _ = camera.project(points)
            drawn = Image.new("L", (camera.width, camera.height), 0)
            ImageDraw.Draw(drawn).polygon([tuple(map(float, p)) for p in uv], fill=1)
            seen_3d = np.asarray(drawn, dtype=bool)
            # the 2D overlay's pixels in this face's tint (the image was black: the tint times its opacity)
            tint = np.round(np.asarray(face.color) * round(255 * TINT_OPACITY) / 255)
            tinted_2d = np.all(np.abs(overlay.astype(np.float64) - tint) <= 2, axis=2)
            iou = (seen_3d & tinted_2d).sum() / (seen_3d | tinted_2d).sum()
            assert seen_3d.sum() > 2000 and iou > 0.9, (face.name, iou)
    finally:
        server.stop()


def test_the_front_is_the_handle_side():
    """DESIGN: a mug's handle along the object's -z axis; the box's front tint marks it, the up tint +y."""
    by_name = {face.name: (face.axis, face.sign) for face in TINTED_FACES}
    assert by_name == {"up": (1, 1), "front": (2, -1)}


def test_symmetric_categories_and_the_noise_model_have_one_definition():
    import evaluate.methods.box as box
    import evaluate.methods.template as template
    import reconstruct.carving as carving
    import sequences.synth.sensor as sensor
    from sequences.annotation import SYMMETRIC_CATEGORIES
    from sequences.sensor_noise import depth_sigma

    assert box.SYMMETRIC_CATEGORIES is SYMMETRIC_CATEGORIES and template.SYMMETRIC_CATEGORIES is SYMMETRIC_CATEGORIES
    assert not hasattr(box, "Y_SYMMETRIC") and not hasattr(template, "Y_SYMMETRIC")
    assert carving.depth_sigma is depth_sigma and sensor.depth_sigma is depth_sigma
    assert depth_sigma(0.4) == pytest.approx(0.0012) and depth_sigma(1.4) == pytest.approx(0.0031)
    assert depth_sigma(np.ones(3, np.float32)).dtype == np.float32  # the carving's float32 images stay float32


def test_display_frames_back_project_through_the_camera():
    """The app's decimated cloud is Camera.backproject's at a stride: the full cloud's every other pixel."""
    camera = Camera(fx=500.0, fy=510.0, cx=300.2, cy=250.7)
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 2.0, camera.shape)
    depth[rng.random(camera.shape) < 0.3] = 0.0
    depth[5, 8] = np.nan
    full, full_index = camera.backproject(depth)
    every_other = np.zeros(camera.shape, bool)
    every_other[::2, ::2] = True
    expected = np.isin(full_index, np.flatnonzero(every_other))
    points, index = camera.backproject(depth, stride=2)
    np.testing.assert_array_equal(index, full_index[expected])
    np.testing.assert_array_equal(points, full[expected])
