"""Analytic test scenes for reconstruct: a known mesh (box, cylinder, cup) rendered into a Redwood-layout folder.

Independent truth for the reconstruct tests: the depth images are ray-cast (Open3D) from a
known mesh at known poses, in front of a wall, optionally with a "hand" (a sphere that moves
relative to the object) and depth noise. The helpers are tested here too.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh
import yaml
from PIL import Image
from scipy.spatial.transform import Rotation

from sequences.camera import Camera

WALL_DEPTH = 1.5  # metres: background wherever nothing else is hit


@dataclass
class Scene:
    root: Path
    mesh: trimesh.Trimesh  # object frame, box-centred
    extents: np.ndarray
    poses: dict[str, np.ndarray]
    camera: Camera


def cup_mesh(radius: float = 0.04, height: float = 0.1, wall: float = 0.006) -> trimesh.Trimesh:
    """An open cup (a cavity from the top, wall and floor ``wall`` thick), axis y, centred on its box."""
    h = height / 2
    profile = np.array([[0, -h], [radius, -h], [radius, h], [radius - wall, h], [radius - wall, -h + wall], [0, -h + wall]])
    cup = trimesh.creation.revolve(profile, sections=96)  # about z, profile's second coordinate along z
    cup.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # z -> y
    cup.apply_translation(-cup.bounds.mean(axis=0))
    return cup


def y_cylinder(radius: float, height: float) -> trimesh.Trimesh:
    mesh = trimesh.creation.cylinder(radius, height, sections=128)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # axis z -> y
    return mesh


def orbit_poses(n: int, distance: float = 0.6, seed: int = 0, upper_only: bool = False, arc_deg: float = 360.0) -> list[np.ndarray]:
    """Object-to-camera poses seeing the object from directions spread over the sphere (or the upper half),
    at azimuths within ``arc_deg`` of the object's +x axis."""
    rng = np.random.default_rng(seed)
    golden = np.pi * (3 - np.sqrt(5))
    i = np.arange(n) + 0.5
    y = 1 - i / n if upper_only else 1 - 2 * i / n  # viewing direction's y (object frame)
    if upper_only:
        y = 0.15 + 0.8 * y
    r = np.sqrt(1 - y**2)
    phi = np.mod(golden * np.arange(n), 2 * np.pi) * (arc_deg / 360.0)
    directions = np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)  # object centre -> camera
    poses = []
    for d in directions:
        z_cam = -d  # camera looks at the object
        x_cam = np.cross([0.0, 1.0, 0.0], z_cam)
        if np.linalg.norm(x_cam) < 1e-6:
            x_cam = np.array([1.0, 0.0, 0.0])
        x_cam /= np.linalg.norm(x_cam)
        y_cam = np.cross(z_cam, x_cam)
        R_cam_in_obj = np.stack([x_cam, y_cam, z_cam], axis=1)  # columns: camera axes in object frame
        roll = Rotation.from_rotvec([0, 0, rng.uniform(-0.5, 0.5)]).as_matrix()
        T = np.eye(4)
        T[:3, :3] = (R_cam_in_obj @ roll).T
        T[:3, 3] = [rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), distance]
        poses.append(T)
    return poses


def render_depth(meshes: list[trimesh.Trimesh], camera: Camera) -> np.ndarray:
    """(H, W) depth of camera-frame meshes, with the wall where nothing is hit."""
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)), o3d.core.Tensor(m.faces.astype(np.uint32)))
    rays = np.zeros((camera.height * camera.width, 6), dtype=np.float32)
    rays[:, 3:] = camera.pixel_rays().reshape(-1, 3)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(camera.shape)
    return np.where(np.isfinite(hit) & (hit < WALL_DEPTH), hit, WALL_DEPTH).astype(np.float32)


def write_scene(
    root: Path,
    mesh: trimesh.Trimesh,
    n_frames: int = 30,
    camera: Camera = Camera(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240),
    noise: bool = False,
    hand: bool = False,
    category: str = "other",
    symmetry: str = "none",
    upper_only: bool = False,
    arc_deg: float = 360.0,
    seed: int = 0,
    extra: trimesh.Trimesh | None = None,
) -> Scene:
    """Render ``mesh`` (object frame) into ``root`` (rgb/, depth/, camera.yaml, annotation.yaml with the true poses);
    ``extra``: a mesh fixed in the object frame beside it (a table it stands on), rendered too but not the object."""
    rng = np.random.default_rng(seed)
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    (root / "camera.yaml").write_text(yaml.safe_dump(camera.to_dict()))
    extents = mesh.extents.copy()
    poses = {}
    frames = {}
    hand_mesh = trimesh.creation.icosphere(2, radius=0.02)
    for i, T in enumerate(orbit_poses(n_frames, seed=seed, upper_only=upper_only, arc_deg=arc_deg)):
        frame_id = f"{i:07d}"
        posed = mesh.copy()
        posed.apply_transform(T)
        meshes = [posed]
        if extra is not None:
            meshes.append(extra.copy().apply_transform(T))
        if hand:
            # a sphere touching the object's side, at a place that changes every frame
            angle = rng.uniform(0, 2 * np.pi)
            centre = np.array([np.cos(angle) * (extents[0] / 2 + 0.02), rng.uniform(-0.3, 0.3) * extents[1], np.sin(angle) * (extents[2] / 2 + 0.02)])
            h = hand_mesh.copy()
            h.apply_translation(centre)
            h.apply_transform(T)
            meshes.append(h)
        depth = render_depth(meshes, camera)
        if noise:
            from reconstruct.carving import depth_sigma

            depth = depth + rng.normal(size=depth.shape).astype(np.float32) * depth_sigma(depth)
        Image.fromarray(np.rint(depth * 1000).astype(np.uint16)).save(root / "depth" / f"{frame_id}.png")
        Image.fromarray(np.full((camera.height, camera.width, 3), 128, np.uint8)).save(root / "rgb" / f"{frame_id}.png")
        poses[frame_id] = T
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        frames[frame_id] = {"position": T[:3, 3].tolist(), "orientation": q.tolist(), "source": "manual"}
    doc = {"sequence": root.name, "category": category, "symmetry": symmetry, "extents": extents.tolist(), "frames": frames}
    (root / "annotation.yaml").write_text(yaml.safe_dump(doc))
    return Scene(root, mesh, extents, poses, camera)


def fscore(a: trimesh.Trimesh, b: trimesh.Trimesh, threshold: float, n: int = 20000, seed: int = 0) -> float:
    """F-score of two meshes at ``threshold`` metres from area-weighted surface samples (cKDTree)."""
    from scipy.spatial import cKDTree

    pa = trimesh.sample.sample_surface(a, n, seed=seed)[0]
    pb = trimesh.sample.sample_surface(b, n, seed=seed + 1)[0]
    precision = np.mean(cKDTree(pb).query(pa)[0] < threshold)
    recall = np.mean(cKDTree(pa).query(pb)[0] < threshold)
    return float(2 * precision * recall / max(precision + recall, 1e-12))


def test_rendered_depth_matches_analytic_plane(tmp_path):
    # a box face seen head-on at 0.6 m: depth = 0.6 - half its depth
    camera = Camera(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    box.apply_translation([0, 0, 0.6])
    depth = render_depth([box], camera)
    assert depth[120, 160] == pytest.approx(0.55, abs=1e-5)
    assert depth[0, 0] == WALL_DEPTH
    # the face spans 0.1 m at 0.55 m: 0.1 / 0.55 * 262.5 = 47.7 pixels wide
    assert abs(int((depth[120] < 1).sum()) - 48) <= 1


def test_fscore_helper_against_known_offsets():
    a = trimesh.creation.icosphere(4, radius=0.05)
    b = trimesh.creation.icosphere(4, radius=0.053)  # 3 mm bigger everywhere
    assert fscore(a, b, 0.005) > 0.99
    assert fscore(a, b, 0.002) < 0.05
