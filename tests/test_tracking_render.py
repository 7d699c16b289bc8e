"""A small independent renderer for tracking tests: a mesh at known poses, ray-cast to Redwood-layout depth and colour.

Also used by the tracking tests until/besides sequences.synth; its own test checks the depth
of a plane against the analytic value.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh
from PIL import Image
from scipy.spatial.transform import Rotation

from annotate.tracking import TrackingConfig
from annotate.tracking.config import scaled_to
from annotate.tracking.frames import FrameStore
from annotate.tracking.tracker import Tracker
from sequences.camera import Camera
from sequences.reader import Sequence, open_sequence


def rendered_scene(root: Path, mesh: trimesh.Trimesh, **render) -> tuple[Sequence, trimesh.Trimesh, dict[str, np.ndarray]]:
    """:func:`render_sequence` of ``mesh`` into ``root`` (``render``: its settings), opened: (sequence, mesh,
    {frame id: true 4x4 pose})."""
    truth = render_sequence(root, mesh, **render)
    return open_sequence(root), mesh, truth


def render_tracker(sequence, mesh: trimesh.Trimesh, **settings) -> Tracker:
    """A tracker of a rendered ``sequence`` of ``mesh`` (no colours, no symmetry), ``settings`` on TrackingConfig
    and the whole configuration scaled to the mesh's size."""
    config = scaled_to(TrackingConfig(**settings), mesh.extents)
    return Tracker(FrameStore(sequence, config.stride, colors=False), mesh.extents, False, config)


def object_offset(rotvec_deg=(0.0, 0.0, 0.0), translation_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A 4x4 object-frame change (``pose @ offset``): the rotation of the rotation vector ``rotvec_deg`` (deg, object
    axes) and the translation ``translation_m`` (m)."""
    offset = np.eye(4)
    offset[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    offset[:3, 3] = translation_m
    return offset


def posed_off(scene, offset: np.ndarray, **settings) -> tuple[Tracker, list[str], dict[str, np.ndarray]]:
    """A rendered ``scene`` (sequence, mesh, truth) whose boxes are all off by the same object-frame ``offset`` (4x4),
    as the placed boxes' mean error leaves them: its tracker (:func:`render_tracker` with ``settings``), its frame ids
    in order and those poses."""
    sequence, mesh, truth = scene
    ids = sorted(truth)
    return render_tracker(sequence, mesh, **settings), ids, {f: truth[f] @ offset for f in ids}


def _o3d_mesh(mesh: trimesh.Trimesh) -> o3d.t.geometry.TriangleMesh:
    legacy = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices), o3d.utility.Vector3iVector(mesh.faces))
    return o3d.t.geometry.TriangleMesh.from_legacy(legacy)


def mug_mesh() -> trimesh.Trimesh:
    """A mug-like object, ShapeNet axes (y up, handle along +z), centred on its box: 8 cm wide, 9 cm tall."""
    body = trimesh.creation.cylinder(radius=0.04, height=0.09, sections=48)
    body.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # axis along y
    handle = trimesh.creation.torus(major_radius=0.022, minor_radius=0.007)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))  # ring in the y-z plane
    handle.apply_translation([0, 0, 0.045])
    mesh = trimesh.util.concatenate([body, handle])
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def can_mesh() -> trimesh.Trimesh:
    body = trimesh.creation.cylinder(radius=0.033, height=0.12, sections=48)
    body.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    return body


def smooth_poses(frames: int, seed: int, distance: float = 0.6) -> list[np.ndarray]:
    """Object-to-camera poses: free rotation (a slowly turning random axis, ~3 deg/frame) and a gentle drift."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed)
    omega = rng.normal(size=3)
    poses = []
    for k in range(frames):
        omega = omega + rng.normal(size=3) * 0.3
        omega = omega / np.linalg.norm(omega) * np.radians(3.0)
        R = Rotation.from_rotvec(omega) * R
        T = np.eye(4)
        T[:3, :3] = R.as_matrix()
        T[:3, 3] = [0.03 * np.sin(k / 15), 0.02 * np.cos(k / 20), distance + 0.03 * np.sin(k / 25)]
        poses.append(T)
    return poses


def render_sequence(
    root: Path, mesh: trimesh.Trimesh, frames: int = 30, seed: int = 0, hand: bool = True, noise: float = 0.0005,
    poses: list[np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Write ``root/rgb`` and ``root/depth`` (Redwood layout) of ``mesh`` at smooth poses (or ``poses``, 4x4 object
    to camera, one per frame); returns {frame id: 4x4 pose}.

    With ``hand``, a skin-coloured sphere touches the object and jumps to another contact point every
    12 frames (a regrasp). Depth gets Gaussian noise of ``noise`` metres, then mm quantisation.
    """
    camera = Camera()
    rng = np.random.default_rng(seed + 1)
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    rays = camera.pixel_rays().reshape(-1, 3)
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    origins = np.zeros_like(rays)
    tensor_rays = o3d.core.Tensor(np.hstack([origins, rays]).astype(np.float32))
    vertex_color = 0.3 + 0.6 * (mesh.vertices - mesh.vertices.min(0)) / np.ptp(mesh.vertices, axis=0)
    contacts = mesh.sample(50, seed=seed) if hasattr(mesh, "sample") else mesh.vertices[:50]
    truth = {}
    for k, pose in enumerate(smooth_poses(frames, seed) if poses is None else poses):
        scene = o3d.t.geometry.RaycastingScene()
        posed = mesh.copy()
        posed.apply_transform(pose)
        scene.add_triangles(_o3d_mesh(posed))
        if hand:
            contact = contacts[(k // 12) % len(contacts)]
            centre_obj = contact * (1 + 0.025 / max(np.linalg.norm(contact), 1e-6))
            sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.025)
            sphere.apply_translation(pose[:3, :3] @ centre_obj + pose[:3, 3])
            scene.add_triangles(_o3d_mesh(sphere))
        hit = scene.cast_rays(tensor_rays)
        t = hit["t_hit"].numpy()
        geometry = hit["geometry_ids"].numpy()
        depth = np.where(np.isfinite(t), t * rays[:, 2], 0.0)
        depth = np.where(depth > 0, depth + rng.normal(size=depth.shape) * noise, 0.0)
        color = np.full((len(rays), 3), 40, dtype=np.uint8)
        on_object = geometry == 0
        prim = hit["primitive_ids"].numpy()
        faces = np.clip(prim[on_object], 0, len(mesh.faces) - 1)
        color[on_object] = (vertex_color[mesh.faces[faces, 0]] * 255).astype(np.uint8)
        color[(geometry == 1) & np.isfinite(t)] = (224, 172, 140)
        frame_id = f"{k:07d}"
        stamp = f"{k * 33333:012d}"
        Image.fromarray(color.reshape(camera.height, camera.width, 3)).save(root / "rgb" / f"{frame_id}-{stamp}.png")
        Image.fromarray(np.round(depth * 1000).astype(np.uint16).reshape(camera.height, camera.width)).save(root / "depth" / f"{frame_id}-{stamp}.png")
        truth[frame_id] = pose
    return truth


def test_renderer_depth_of_a_plane(tmp_path):
    """A large box face facing the camera at 0.6 m: every hit pixel's depth is 600 mm (independent truth)."""
    plate = trimesh.creation.box(extents=[0.2, 0.2, 0.01])
    pose = np.eye(4)
    pose[2, 3] = 0.605
    root = tmp_path / "seq"
    camera = Camera()
    scene = o3d.t.geometry.RaycastingScene()
    posed = plate.copy()
    posed.apply_transform(pose)
    scene.add_triangles(_o3d_mesh(posed))
    rays = camera.pixel_rays().reshape(-1, 3)
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    hit = scene.cast_rays(o3d.core.Tensor(np.hstack([np.zeros_like(rays), rays]).astype(np.float32)))
    t = hit["t_hit"].numpy()
    depth = t * rays[:, 2]
    assert np.allclose(depth[np.isfinite(t)], 0.6, atol=1e-5)
    # a plate 0.2 m wide at 0.6 m covers 0.2 * 525 / 0.6 = 175 pixels across
    assert abs(np.isfinite(t).reshape(480, 640)[240].sum() - 175) <= 2
    truth = render_sequence(root, mug_mesh(), frames=2, seed=0, hand=False)
    assert sorted(truth) == ["0000000", "0000001"]
    assert len(list((root / "depth").iterdir())) == 2
