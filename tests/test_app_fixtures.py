"""A tiny synthetic Redwood-layout sequence for the app's tests, rendered with Open3D ray casting.

A box of known size and pose (moving a little from frame to frame) in front of a back wall;
``make_sequence`` writes rgb/*.jpg, depth/*.png (16-bit mm) and returns the true poses.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d
from PIL import Image
from scipy.spatial.transform import Rotation

from sequences.camera import Camera

if TYPE_CHECKING:
    from annotate.app import App

#: True object box (full sides, m): object x, y (up), z (front).
TRUE_EXTENTS = np.array([0.08, 0.12, 0.06])


def true_pose(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Pose of frame k: position (m, camera frame), orientation x y z w (object y up, turning about it)."""
    upright = Rotation.from_euler("x", 180, degrees=True)  # object y -> camera -y
    turn = Rotation.from_euler("y", 8.0 * k + 20.0, degrees=True)
    position = np.array([0.01 * k - 0.01, 0.005 * k, 0.7 + 0.01 * k])
    return position, (upright * turn).as_quat()


def render(camera: Camera, position, orientation, extents=TRUE_EXTENTS, wall: float = 1.2, shape: str = "box") -> tuple[np.ndarray, np.ndarray]:
    """Colour (H, W, 3) uint8 and depth (H, W) float32 m of the object in front of a wall at ``wall`` m.

    ``shape`` "box" fills the extents; "cylinder" is the cylinder about object y inscribed in them.
    """
    scene = o3d.t.geometry.RaycastingScene()
    if shape == "cylinder":
        box = o3d.geometry.TriangleMesh.create_cylinder(radius=extents[0] / 2, height=extents[1], resolution=64, split=1)
        box.rotate(Rotation.from_euler("x", -90, degrees=True).as_matrix(), center=(0, 0, 0))  # open3d's z axis to y
    else:
        box = o3d.geometry.TriangleMesh.create_box(*extents)
        box.translate(-np.asarray(extents) / 2)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(orientation).as_matrix()
    T[:3, 3] = position
    box.transform(T)
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
    wall_mesh = o3d.geometry.TriangleMesh.create_box(4.0, 4.0, 0.01)
    wall_mesh.translate([-2.0, -2.0, wall])
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(wall_mesh))
    rays = camera.pixel_rays()
    directions = rays / np.linalg.norm(rays, axis=2, keepdims=True)
    tensor = np.concatenate([np.zeros_like(directions), directions], axis=2).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(tensor))
    t = hit["t_hit"].numpy()
    ids = hit["geometry_ids"].numpy()
    normals = hit["primitive_normals"].numpy()
    depth = np.where(np.isfinite(t), t * directions[..., 2], 0.0).astype(np.float32)
    shade = np.clip(np.abs(np.sum(normals * directions, axis=2)), 0.2, 1.0)
    base = np.where((ids == 0)[..., None], np.array([200, 60, 40]), np.array([90, 110, 130]))
    u = np.arange(camera.width)[None, :]
    checker = ((u // 16 + np.arange(camera.height)[:, None] // 16) % 2)[..., None] * 25  # texture for the wall
    color = np.clip(base * shade[..., None] + np.where((ids == 0)[..., None], 0, checker), 0, 255).astype(np.uint8)
    return color, depth


def make_sequence(root: Path, frames: int = 4, shape: str = "box", extents=TRUE_EXTENTS) -> tuple[Path, list[tuple[np.ndarray, np.ndarray]]]:
    """Write a ``frames``-frame sequence of a ``shape`` under ``root``; returns (root, true poses per frame)."""
    root = Path(root)
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    camera = Camera()
    poses = []
    for k in range(frames):
        position, orientation = true_pose(k)
        color, depth = render(camera, position, orientation, extents, shape=shape)
        stamp = 33_333 * k
        Image.fromarray(color).save(root / "rgb" / f"{k + 1:07d}-{stamp:012d}.jpg", quality=92)
        Image.fromarray(np.round(depth * 1000).astype(np.uint16)).save(root / "depth" / f"{k + 1:07d}-{stamp:012d}.png")
        poses.append((position, orientation))
    return root, poses


def test_synthetic_sequence_depth_matches_the_box(tmp_path):
    """The rendered depth at the box's centre pixel is the front face's depth (independent check of the fixture)."""
    from sequences.reader import open_sequence

    root, poses = make_sequence(tmp_path / "seq", frames=1)
    seq = open_sequence(root)
    position, orientation = poses[0]
    uv, _ = seq.camera.project(position[None])
    u, v = np.round(uv[0]).astype(int)
    depth = seq.depth(0)
    # the ray through the centre hits a face; it must lie within the box's half-diagonal of the centre
    hit = depth[v, u]
    assert abs(hit - position[2]) <= np.linalg.norm(TRUE_EXTENTS) / 2
    assert hit < position[2]  # the visible face is in front of the centre
    assert abs(depth[5, 5] - 1.2) < 0.0015  # the wall, to the millimetre of the PNG


@contextmanager
def served_app(source: Path, tmp_path: Path) -> Iterator["App"]:
    """The browser app on a copy of the sequence folder ``source`` (copied into ``tmp_path``), served on a free
    local port; closed, and its server stopped, afterwards."""
    import viser

    from annotate.app import App
    from sequences.reader import open_sequence

    root = tmp_path / source.name
    shutil.copytree(source, root)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = App(server, open_sequence(root))
    try:
        yield app
    finally:
        app.close()
        server.stop()
