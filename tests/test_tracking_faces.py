"""A box-like object's frame from its faces (faces.py, engine._snap_faces): known rotations of sampled normals,
the shapes it must refuse, a rendered camera whose boxes are all tilted, and a bowl tilted off its foot."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_tracking_render import object_offset, posed_off, render_tracker

from annotate.tracking import TrackingConfig
from annotate.tracking.engine import _snap_faces, _snap_hinge
from annotate.tracking.faces import box_like, face_rotation, hinge_rotation, tilt_onto_axis
from annotate.tracking.refine import build_model
from sequences.synth.shapes import procedural_mesh

SHARE, TOTAL = TrackingConfig.min_face_share, TrackingConfig.min_faces_total


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())))


def _jitter(normals: np.ndarray, deg: float, rng: np.random.Generator) -> np.ndarray:
    """Each normal turned by a random rotation of about ``deg`` (the normals' estimation noise)."""
    turns = Rotation.from_rotvec(rng.normal(0.0, np.radians(deg) / np.sqrt(3), (len(normals), 3)))
    return turns.apply(normals)


def _box_normals(sides=(0.12, 0.08, 0.06), count: int = 6000, seed: int = 0) -> np.ndarray:
    """Normals of points spread over a box's faces by area, either sign (as estimated normals come)."""
    rng = np.random.default_rng(seed)
    x, y, z = sides
    areas = np.array([y * z, x * z, x * y] * 2)
    face = rng.choice(6, size=count, p=areas / areas.sum())
    sign = rng.choice([-1.0, 1.0], size=(count, 1))
    return sign * np.vstack([np.eye(3), -np.eye(3)])[face]


def test_a_turned_box_is_turned_back_to_its_axes():
    rng = np.random.default_rng(1)
    truth = Rotation.from_rotvec(np.radians(3.0) * np.array([0.48, -0.6, 0.64])).as_matrix()
    normals = _jitter(_box_normals(), 3.0, rng) @ truth.T  # the model's normals, its frame turned by 3 deg
    rotation, counts = face_rotation(normals)
    assert rotation is not None
    # the fit undoes the turn: measured 0.02 deg left of 3
    assert _angle_deg(rotation @ truth) < 0.1
    assert box_like(counts, len(normals), SHARE, TOTAL)


def test_shapes_whose_faces_are_not_the_frame_are_refused():
    rng = np.random.default_rng(2)
    # a mug's body: a cylinder's side faces every way about y, with its two caps
    around = rng.uniform(0, 2 * np.pi, 4000)
    side = np.stack([np.cos(around), np.zeros_like(around), np.sin(around)], 1)
    caps = np.repeat([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], 600, axis=0)
    cylinder = _jitter(np.vstack([side, caps]), 2.0, rng)
    rotation, counts = face_rotation(cylinder)
    assert rotation is None or not box_like(counts, len(cylinder), SHARE, TOTAL)
    # a laptop: base (y) and a lid opened 110 deg, their thin sides a few normals
    lid = Rotation.from_euler("x", -20, degrees=True).apply(np.repeat([[0.0, 0.0, 1.0]], 3000, axis=0))
    laptop = np.vstack([np.repeat([[0.0, 1.0, 0.0]], 3000, axis=0), lid, np.repeat([[1.0, 0.0, 0.0]], 20, axis=0)])
    rotation, counts = face_rotation(_jitter(laptop, 2.0, rng))
    assert rotation is None or not box_like(counts, len(laptop), SHARE, TOTAL)


def test_too_few_normals_in_the_cones_give_no_rotation():
    rotation, _ = face_rotation(np.repeat([[0.6, 0.8, 0.0]], 100, axis=0))  # 37 deg from x, 53 from y: no cone
    assert rotation is None


@pytest.mark.slow
def test_camera_boxes_tilted_together_are_turned_back_onto_its_faces(rendered_camera):
    sequence, mesh, truth = rendered_camera
    tracker, ids, poses = posed_off(rendered_camera, object_offset(rotvec_deg=2.5 * np.array([0.6, 0.0, 0.8])))
    snap = _snap_faces(tracker, build_model(tracker, poses, tracker.config.max_global_frames, [ids[0]]))
    assert snap is not None
    assert np.array_equal(snap[:3, 3], np.zeros(3)), "a rotation about the box centre"
    left = [_angle_deg((poses[f] @ snap)[:3, :3].T @ truth[f][:3, :3]) for f in ids]
    # measured: 0.55 deg left of 2.5. The same snap at the true poses turns 0.54 deg: these 12 frames see three
    # faces, and the model's normals lean over their edges within the 10 deg cones (0.11 deg with 4 deg cones)
    assert max(left) < 0.8, left
    # a turn beyond max_face_snap_deg is not the placed boxes' error: refused
    strict = render_tracker(sequence, mesh, max_face_snap_deg=1.0)
    assert _snap_faces(strict, build_model(strict, poses, strict.config.max_global_frames, [ids[0]])) is None


def _bowl_normals(count: int = 20000, seed: int = 0) -> np.ndarray:
    """Face normals at points spread over a procedural bowl (foot, curved wall, inner bottom) by area, object frame."""
    import trimesh

    mesh = procedural_mesh("bowl", np.random.default_rng(seed))
    _, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return mesh.face_normals[faces]


def test_a_tilted_bowl_is_turned_upright_by_its_foot_and_bottom():
    rng = np.random.default_rng(4)
    normals = _jitter(_bowl_normals(), 3.0, rng)
    # a side the hand hides: the wall's normals on +x are missing (the fit must not lean to the other side)
    normals = normals[~((normals[:, 0] > 0.3) & (np.abs(normals[:, 1]) < 0.9))]
    tilt = Rotation.from_rotvec(np.radians([2.0, 0.0, -1.5])).as_matrix()
    spin = Rotation.from_rotvec(np.radians([0.0, 40.0, 0.0])).as_matrix()  # free for symmetry y: left as it is
    truth = tilt @ spin
    rotation, count = tilt_onto_axis(normals @ truth.T)
    assert rotation is not None and count > 0.03 * len(normals)
    # y comes back onto the axis: measured 0.08 deg of the 2.5 deg tilt left (3 deg cones: 0.20, 7 deg: 0.07)
    y = rotation @ truth @ np.array([0.0, 1.0, 0.0])
    assert np.degrees(np.arccos(np.clip(y[1], -1.0, 1.0))) < 0.2
    # each step turns about x and z only: the spin left is of second order in the steps (1e-5 rad here)
    assert abs(Rotation.from_matrix(rotation).as_rotvec()[1]) < 1e-4


def test_a_body_without_faces_across_its_axis_gives_no_tilt():
    rng = np.random.default_rng(5)
    around = rng.uniform(0, 2 * np.pi, 4000)
    side = np.stack([np.cos(around), np.zeros_like(around), np.sin(around)], 1)  # an open tube's wall
    rotation, count = tilt_onto_axis(_jitter(side, 2.0, rng))
    assert rotation is None and count < 30
    # a few normals along the axis (25, under the 30 the fit needs): a stray patch, not a face
    caps = np.repeat([[0.0, 1.0, 0.0]], 25, axis=0)
    rotation, count = tilt_onto_axis(np.vstack([side, caps]))
    assert rotation is None and count == 25
    rotation, count = tilt_onto_axis(np.vstack([side, caps, caps[:5]]))
    assert rotation is not None and count == 30


def _laptop_normals(seed: int, count: int = 20000) -> np.ndarray:
    """Face normals at points spread over a procedural laptop (base, lid opened 95-120 deg) by area, object frame."""
    import trimesh

    mesh = procedural_mesh("laptop", np.random.default_rng(seed))
    _, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return mesh.face_normals[faces]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_turned_laptop_is_turned_back_by_its_base_and_lid(seed):
    rng = np.random.default_rng(10 + seed)
    normals = _jitter(_laptop_normals(seed), 3.0, rng)
    # the side the hand hides: the base's underside is missing
    normals = normals[normals[:, 1] > -0.9]
    truth = Rotation.from_rotvec(np.radians([1.2, -1.0, 0.8])).as_matrix()  # 1.8 deg, about all three axes
    rotation, shares = hinge_rotation(normals @ truth.T)
    assert rotation is not None
    # measured 0.03-0.05 deg left of 1.8; the spin about y comes from the lid alone (the base's top faces along it)
    assert _angle_deg(rotation @ truth) < 0.15
    config = TrackingConfig()
    assert shares[1] >= config.min_hinge_plane_share, shares


def test_a_laptop_seen_mostly_on_its_lid_is_turned_back_too():
    """Frames that face the screen see little of the base: a model can hold only a few per cent of its normals along
    the base's faces (4-10 % on the dev laptop). The cone's normals need only be enough to fit (30), not a share."""
    rng = np.random.default_rng(13)
    normals = _jitter(_laptop_normals(3), 3.0, rng)
    along_base = np.abs(normals[:, 1]) > 0.95
    keep = ~along_base | (rng.uniform(size=len(normals)) < 0.02 * len(normals) / max(along_base.sum(), 1))
    normals = normals[keep & (normals[:, 1] > -0.9)]  # about 2 % of what is left faces along the base, none below
    truth = Rotation.from_rotvec(np.radians([1.0, -0.8, 1.5])).as_matrix()
    rotation, shares = hinge_rotation(normals @ truth.T)
    assert rotation is not None and shares[0] < 0.05, shares
    assert shares[1] >= TrackingConfig().min_hinge_plane_share, shares
    assert _angle_deg(rotation @ truth) < 0.5  # of 2.0 deg (0.34 left: the base's few normals fix the tilt less well)


def test_a_lid_alone_fixes_the_spin_and_the_base_alone_does_not():
    rng = np.random.default_rng(20)
    base = np.repeat([[0.0, 1.0, 0.0]], 3000, axis=0)
    lid = Rotation.from_euler("x", -20, degrees=True).apply(np.repeat([[0.0, 0.0, 1.0]], 3000, axis=0))
    spin = Rotation.from_rotvec(np.radians([0.0, 1.5, 0.0])).as_matrix()
    rotation, _ = hinge_rotation(_jitter(np.vstack([base, lid]), 1.0, rng) @ spin.T)
    assert rotation is not None and _angle_deg(rotation @ spin) < 0.1
    # the base alone: its normals lie in the plane whatever the spin, which is left as it is (not set by their noise)
    rotation, _ = hinge_rotation(_jitter(base, 1.0, rng) @ spin.T)
    assert rotation is not None and abs(Rotation.from_matrix(rotation).as_rotvec()[1]) < 1e-4


def test_shapes_that_are_not_hinged_fall_short_of_the_plane_share():
    rng = np.random.default_rng(21)
    config = TrackingConfig()
    around = rng.uniform(0, 2 * np.pi, 4000)
    side = np.stack([np.cos(around), np.zeros_like(around), np.sin(around)], 1)  # a mug's body, with its caps
    caps = np.repeat([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], 600, axis=0)
    rotation, shares = hinge_rotation(_jitter(np.vstack([side, caps]), 2.0, rng))
    assert rotation is None or shares[1] < config.min_hinge_plane_share, shares
    assert hinge_rotation(np.repeat([[0.6, 0.8, 0.0]], 100, axis=0))[0] is None  # nothing in the cone


@pytest.mark.slow
def test_laptop_boxes_tilted_together_are_turned_back_onto_its_base_and_lid(rendered_laptop):
    sequence, mesh, truth = rendered_laptop
    tracker, ids, poses = posed_off(rendered_laptop, object_offset(rotvec_deg=(1.5, -1.2, 1.0)))  # 2.2 deg
    model = build_model(tracker, poses, len(ids), [ids[0]])
    snap = _snap_hinge(tracker, model)
    assert snap is not None
    left = [_angle_deg((poses[f] @ snap)[:3, :3].T @ truth[f][:3, :3]) for f in ids]
    # measured: 0.08 deg left of 2.2 (12 frames without a hand; 8 % of the model's normals lie in the base's cone)
    assert max(left) < 0.3, left
    assert _snap_hinge(render_tracker(sequence, mesh, max_face_snap_deg=1.0), model) is None


@pytest.mark.parametrize("scan", ["camera_canon_len_norm", "mug_daniel_norm"])
def test_real_scans_that_are_not_hinged_are_refused(nocs_dir, scan):
    """A real camera (not box-like either: its lens, grip and rounded body) and a real mug from the NOCS scans leave
    the hinge snap alone: their normals fall far short of its shares."""
    import trimesh

    from sequences.synth.shapes import load_mesh

    path = nocs_dir / "obj_models" / "real_test" / f"{scan}.obj"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    mesh = load_mesh(path)
    _, faces = trimesh.sample.sample_surface(mesh, 20000, seed=0)
    rotation, shares = hinge_rotation(mesh.face_normals[faces])
    config = TrackingConfig()
    # the camera holds 14 % of its normals in the plane, the mug 6.9 % (the gate: 35 %)
    assert rotation is None or shares[1] < config.min_hinge_plane_share, shares
