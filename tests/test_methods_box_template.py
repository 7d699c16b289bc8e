"""The weights-free methods `box` and `template` against renders of known meshes at known poses."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy import ndimage
from scipy.spatial.transform import Rotation

from evaluate.geometry import quat_to_matrix
from evaluate.metrics import rotation_error
from evaluate.rendering import MeshRenderer
from evaluate.methods.base import Prediction
from evaluate.methods.box import BoxMethod, masked_points
from evaluate.methods.template import (
    TemplateMethod,
    fibonacci_sphere,
    rotations_taking_y_to,
    super_fibonacci_rotations,
    umeyama,
)
from evaluate.methods.templates import TEMPLATE_CATEGORIES, builtin_template
from sequences.camera import Camera

CAMERA = Camera()


def render(mesh: trimesh.Trimesh, rotation: np.ndarray, position: np.ndarray, camera: Camera = CAMERA):
    """Depth (H, W) float32 m (0 = miss) and mask (H, W) bool of ``mesh`` posed object->camera, by ray casting."""
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, position
    depth = MeshRenderer(mesh, camera).depth(pose)
    return depth, depth > 0


def frame(y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Object->camera rotation with object y and (the part of) z given in camera coordinates."""
    y = y / np.linalg.norm(y)
    z = z - (z @ y) * y
    z = z / np.linalg.norm(z)
    return np.stack([np.cross(y, z), y, z], axis=1)


UPRIGHT = frame(np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, -1.0]))  # y up in the image, z towards the camera


@pytest.fixture(scope="module")
def template_method() -> TemplateMethod:
    return TemplateMethod()


# ------------------------------------------------------------------------------------ building blocks


def test_builtin_templates_are_box_centred_shapenet_frames():
    for category in TEMPLATE_CATEGORIES:
        mesh = builtin_template(category)
        np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
        assert mesh.is_watertight and mesh.volume > 0
    bottle = builtin_template("bottle")
    # The neck is at +y: the widest cross-section near the top is the neck's.
    top = bottle.vertices[bottle.vertices[:, 1] > 0.09]
    assert np.abs(top[:, [0, 2]]).max() == pytest.approx(0.013, abs=1e-6)
    mug = builtin_template("mug")
    assert mug.extents[2] > mug.extents[0] + 0.02  # the handle sticks out along +z
    assert mug.vertices[:, 2].max() > -mug.vertices[:, 2].min() - 1e-9


def test_super_fibonacci_rotations_cover_so3():
    rotations = Rotation.from_matrix(super_fibonacci_rotations(3000))
    probes = Rotation.random(500, random_state=np.random.default_rng(3).integers(1 << 31))
    # Angle from each random probe to its nearest hypothesis: cos(angle / 2) = |<q1, q2>|.
    dots = np.abs(probes.as_quat() @ rotations.as_quat().T).max(axis=1)
    worst = np.degrees(2 * np.arccos(np.clip(dots, -1, 1))).max()
    # The spiral's worst gap is about 14 degrees; 3000 random rotations leave gaps over 20 degrees.
    assert worst < 16.0
    assert np.allclose(np.linalg.det(rotations.as_matrix()), 1.0)


def test_rotations_taking_y_to_directions():
    directions = fibonacci_sphere(200)
    rotations = rotations_taking_y_to(directions)
    np.testing.assert_allclose(rotations[:, :, 1], directions, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", rotations, rotations), np.broadcast_to(np.eye(3), (200, 3, 3)), atol=1e-12)
    assert np.allclose(np.linalg.det(rotations), 1.0)


def test_umeyama_recovers_a_known_similarity():
    rng = np.random.default_rng(5)
    source = rng.normal(size=(50, 3))
    rotation = Rotation.random(random_state=11).as_matrix()
    target = 1.7 * source @ rotation.T + np.array([0.1, -0.2, 0.3])
    scale, found, translation = umeyama(source, target)
    assert scale == pytest.approx(1.7, rel=1e-12)
    np.testing.assert_allclose(found, rotation, atol=1e-12)
    np.testing.assert_allclose(translation, [0.1, -0.2, 0.3], atol=1e-12)


def test_masked_points_drop_background_pixels_on_the_mask():
    mesh = builtin_template("can")
    depth, mask = render(mesh, UPRIGHT, np.array([0.0, 0.0, 0.7]))
    clean = masked_points(depth, mask, CAMERA)
    assert len(clean) == mask.sum()  # nothing of the object itself is dropped
    # Bleed the mask 4 pixels onto a wall 1 m behind the object.
    bled = ndimage.binary_dilation(mask, iterations=4)
    wall = np.where(mask, depth, np.float32(1.7))
    points = masked_points(wall, bled, CAMERA)
    assert len(points) == mask.sum()
    assert points[:, 2].max() < 0.8


# ------------------------------------------------------------------------------------ box


def test_box_upright_can_position_extents_and_axis():
    mesh = builtin_template("can")
    position = np.array([0.05, 0.03, 0.8])
    rotation = frame(np.array([0.0, -1.0, 0.0]), np.array([0.3, 0.0, -1.0]))
    depth, mask = render(mesh, rotation, position)
    prediction = BoxMethod().inference(np.zeros(depth.shape + (3,), np.uint8), depth, mask, "can", CAMERA)
    assert isinstance(prediction, Prediction)
    assert np.linalg.norm(prediction.position - position) < 0.02
    np.testing.assert_allclose(prediction.extents, mesh.extents, rtol=0.1)
    predicted = quat_to_matrix(prediction.orientation)
    assert rotation_error(rotation, predicted, "y") < 10.0
    assert np.linalg.det(predicted) == pytest.approx(1.0)
    # The reconstruction is the observed points in the predicted object frame, inside the box.
    assert np.all(np.abs(prediction.reconstruction) <= prediction.extents / 2 + 0.01)


def test_box_finds_a_tilted_bottles_neck():
    mesh = builtin_template("bottle")
    position = np.array([-0.04, 0.02, 0.75])
    rotation = frame(np.array([0.8, 0.5, -0.3]), np.array([0.0, 0.0, -1.0]))  # pointing right and down
    depth, mask = render(mesh, rotation, position)
    prediction = BoxMethod().inference(None, depth, mask, "bottle", CAMERA)
    assert rotation_error(rotation, quat_to_matrix(prediction.orientation), "y") < 10.0
    assert np.linalg.norm(prediction.position - position) < 0.02
    np.testing.assert_allclose(prediction.extents, mesh.extents, rtol=0.15)


# ------------------------------------------------------------------------------------ template


def test_template_recovers_a_tilted_bottle(template_method):
    mesh = builtin_template("bottle")
    rotation = Rotation.random(random_state=2024).as_matrix()
    position = np.array([0.03, -0.05, 0.7])
    depth, mask = render(mesh, rotation, position)
    prediction = template_method.inference(None, depth, mask, "bottle", CAMERA)
    assert rotation_error(rotation, quat_to_matrix(prediction.orientation), "y") < 10.0
    assert np.linalg.norm(prediction.position - position) < 0.01
    np.testing.assert_allclose(prediction.extents, mesh.extents, rtol=0.05)
    assert isinstance(prediction.reconstruction, trimesh.Trimesh)
    np.testing.assert_allclose(prediction.reconstruction.extents, prediction.extents, rtol=1e-9)


def test_template_recovers_an_upside_down_mug_with_its_handle(template_method):
    mesh = builtin_template("mug")
    # Upside down and tilted towards the camera, handle pointing to the image's right.
    rotation = frame(np.array([0.2, 0.8, -0.55]), np.array([1.0, 0.0, 0.2]))
    position = np.array([0.0, 0.04, 0.65])
    depth, mask = render(mesh, rotation, position)
    prediction = template_method.inference(None, depth, mask, "mug", CAMERA)
    assert rotation_error(rotation, quat_to_matrix(prediction.orientation), "none") < 10.0
    assert np.linalg.norm(prediction.position - position) < 0.01
    np.testing.assert_allclose(prediction.extents, mesh.extents, rtol=0.05)


def test_template_fits_a_scaled_template_from_a_folder_deterministically(tmp_path):
    builtin_template("bowl").export(tmp_path / "bowl.obj")
    method = TemplateMethod(templates=tmp_path)
    mesh = builtin_template("bowl")
    mesh.apply_scale(1.2)  # a bigger bowl than the template
    rotation = Rotation.from_euler("xz", [-120.0, 35.0], degrees=True).as_matrix()  # seen from below, tilted
    position = np.array([-0.02, 0.0, 0.8])
    depth, mask = render(mesh, rotation, position)
    first = method.inference(None, depth, mask, "bowl", CAMERA)
    second = method.inference(None, depth, mask, "bowl", CAMERA)
    assert rotation_error(rotation, quat_to_matrix(first.orientation), "y") < 10.0
    assert np.linalg.norm(first.position - position) < 0.01
    np.testing.assert_allclose(first.extents, mesh.extents, rtol=0.05)
    np.testing.assert_array_equal(first.orientation, second.orientation)
    np.testing.assert_array_equal(first.position, second.position)


def test_template_turns_a_can_upright():
    mesh = builtin_template("can")
    rotation = frame(np.array([0.3, 0.9, 0.2]), np.array([0.0, 0.0, -1.0]))  # upside down
    depth, mask = render(mesh, rotation, np.array([0.0, 0.0, 0.6]))
    prediction = TemplateMethod({"hypotheses": 500, "symmetric_hypotheses": 150}).inference(None, depth, mask, "can", CAMERA)
    predicted = quat_to_matrix(prediction.orientation)
    # The shape does not tell top from bottom: the up prior picks the flip whose y points up in the image.
    assert rotation_error(rotation @ np.diag([1.0, -1.0, -1.0]), predicted, "y") < 10.0
    assert predicted[1, 1] < 0


def test_a_template_prepared_once_is_read_back_bit_for_bit(template_method, tmp_path):
    """prepare_shared builds a category's template once and writes it; another method (a batch's next unit) reads it
    instead of building it, to the same arrays and the same prediction; a file that is not a template is rebuilt
    over, and a category without a template is left to its samples."""
    from evaluate.methods.template import FittedTemplate

    writer = TemplateMethod()
    writer.prepare_shared(["mug", "sofa"], tmp_path)
    written = sorted(tmp_path.iterdir())
    assert [p.name.split("-")[0] for p in written] == ["mug"]
    reader = TemplateMethod()
    reader.prepare_shared(["mug"], tmp_path)
    built, read = template_method.template("mug"), reader.template("mug")
    for name in (*FittedTemplate.ARRAYS, "voxel"):
        a, b = np.asarray(getattr(built, name)), np.asarray(getattr(read, name))
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    np.testing.assert_array_equal(read.mesh.vertices, built.mesh.vertices)
    np.testing.assert_array_equal(read.mesh.faces, built.mesh.faces)
    rotation = frame(np.array([0.1, -0.9, 0.3]), np.array([0.5, 0.0, -1.0]))
    depth, mask = render(builtin_template("mug"), rotation, np.array([0.01, 0.0, 0.7]))
    one, two = template_method.inference(None, depth, mask, "mug", CAMERA), reader.inference(None, depth, mask, "mug", CAMERA)
    for field in ("position", "orientation", "extents"):
        np.testing.assert_array_equal(getattr(one, field), getattr(two, field))
    np.testing.assert_array_equal(one.reconstruction.vertices, two.reconstruction.vertices)
    written[0].write_bytes(b"not an npz")
    again = TemplateMethod()
    again.prepare_shared(["mug"], tmp_path)
    assert np.array_equal(again.template("mug").distance, built.distance)
    assert FittedTemplate.from_npz(written[0]).points.shape == built.points.shape  # written again, whole
    with pytest.raises(ValueError, match="no template for category 'sofa'"):
        again.template("sofa")


# ------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize("method_class", [BoxMethod, TemplateMethod])
def test_empty_or_depthless_mask_is_a_value_error(method_class):
    method = method_class()
    depth = np.full((480, 640), 0.7, np.float32)
    with pytest.raises(ValueError, match="empty mask or no depth"):
        method.inference(None, depth, np.zeros((480, 640), bool), "mug", CAMERA)
    mask = np.zeros((480, 640), bool)
    mask[200:260, 300:360] = True
    with pytest.raises(ValueError, match="empty mask or no depth"):
        method.inference(None, np.zeros_like(depth), mask, "mug", CAMERA)
    with pytest.raises(ValueError, match="mask shape"):
        method.inference(None, depth, mask[:100], "mug", CAMERA)
    with pytest.raises(ValueError, match="floating point"):
        method.inference(None, (depth * 1000).astype(np.uint16), mask, "mug", CAMERA)


def test_unknown_template_category_and_options_are_value_errors(tmp_path):
    depth, mask = render(builtin_template("can"), UPRIGHT, np.array([0.0, 0.0, 0.6]))
    with pytest.raises(ValueError, match="no template for category 'laptop'"):
        TemplateMethod().inference(None, depth, mask, "laptop", CAMERA)
    with pytest.raises(ValueError, match="unknown template method options"):
        TemplateMethod({"hypotheses": 10, "speed": "fast"})
    with pytest.raises(ValueError, match="unknown box method options"):
        BoxMethod({"percentile": 5})
    with pytest.raises(ValueError, match="template folder does not exist"):
        TemplateMethod(templates=tmp_path / "missing")
    (tmp_path / "mug.obj").write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match="mug.obj"):
        TemplateMethod(templates=tmp_path).inference(None, depth, mask, "mug", CAMERA)


def test_template_fits_a_shallower_wider_bowl(template_method):
    mesh = builtin_template("bowl")
    mesh.apply_transform(np.diag([1.1, 0.8, 1.1, 1.0]))  # other proportions than the template's
    rotation = frame(np.array([0.5, -0.6, -0.6]), np.array([0.0, 0.0, 1.0]))
    position = np.array([0.02, 0.03, 0.7])
    depth, mask = render(mesh, rotation, position)
    prediction = template_method.inference(None, depth, mask, "bowl", CAMERA)
    assert rotation_error(rotation, quat_to_matrix(prediction.orientation), "y") < 10.0
    assert np.linalg.norm(prediction.position - position) < 0.01
    np.testing.assert_allclose(prediction.extents, mesh.extents, rtol=0.06)
    # With proportions held, the extents cannot follow: the stretch is what fits them.
    rigid = TemplateMethod({"stretch": 1.0}).inference(None, depth, mask, "bowl", CAMERA)
    ratio = rigid.extents[1] / rigid.extents[0]
    assert ratio == pytest.approx(builtin_template("bowl").extents[1] / builtin_template("bowl").extents[0], rel=1e-9)
