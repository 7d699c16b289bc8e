"""How well a synthetic capture shows its object, from the scene's geometry (no image rendered).

An annotator capturing an object for reconstruction shows it from every side and regrasps so that
what the hand covered is shown free later. This module measures that on a :class:`generate.Scene`'s
trajectory and hand (object frame = ShapeNet axes, camera frame = OpenCV, metres):

- the smallest angle between the object's +y axis and the direction toward the camera (camera
  -z: looking into an opening) and away from it (camera +z: looking at the bottom);
- per grasp, the contact patch: points of the object's surface within CONTACT of the hand's
  palm, fingers or thumb during that hold, on the hand's side of the surface; and the share of them seen unobstructed (first ray hit,
  facing the camera within SEEN_INCIDENCE) in at least one held frame of *another* grasp;
- the share of the whole surface that no frame shows unobstructed (first hit, facing within
  SEEN_INCIDENCE);
- per grasp, the hand's space next to the surface (hand mesh vertices motion.HAND_SPACE off the
  surface): the share of it seen free (in front of the first surface along the ray) in at least
  one frame where that grasp does not hold the object (what a carving needs to remove the hand).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh

from .motion import HAND_SPACE, HandState, Trajectory
from .scene import Layout, elbow_at, hand_parts, upper_arm_part

#: Surface points this close to the hand (metres) count as covered by it.
CONTACT = 0.012
#: A surface point counts as seen when the ray meets it first and at most this far from its normal (degrees).
SEEN_INCIDENCE = 75.0
#: Margin (metres) between a point and the first hit along its ray: "the hit is this point" / "the point is free".
MARGIN = 0.002


@dataclass
class Coverage:
    """Coverage figures of one scene (angles in degrees, shares in 0..1, one entry per grasp)."""

    opening_deg: float  # smallest angle between object +y and the direction toward the camera
    bottom_deg: float  # smallest angle between object +y and the direction away from the camera
    contact_seen: list[float]  # per grasp: share of its contact patch seen unobstructed during another grasp
    hand_space_free: list[float]  # per grasp: share of the hand's space near the surface seen free when it is elsewhere
    unseen: float = 0.0  # share of the whole surface no frame shows unobstructed (a deep cavity's floor, under a hand)


def _surface_samples(mesh: trimesh.Trimesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    points, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return points, np.asarray(mesh.face_normals)[face]


def _first_hits(parts_vertices: np.ndarray, parts_faces: np.ndarray, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance along the ray from the camera centre toward each point to the first triangle hit, and the ray lengths."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(parts_vertices.astype(np.float32)), o3d.core.Tensor(parts_faces.astype(np.uint32)))
    length = np.linalg.norm(points_cam, axis=1)
    rays = np.concatenate([np.zeros_like(points_cam), points_cam / length[:, None]], axis=1).astype(np.float32)
    return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64), length


def measure(mesh: trimesh.Trimesh, trajectory: Trajectory, hands: list[HandState], layout: Layout, samples: int = 4000, seed: int = 0) -> Coverage:
    """Coverage of ``mesh`` moved by ``trajectory`` and held by ``hands`` (one per frame)."""
    R = trajectory.rotations
    up = R[:, :, 1]  # object +y in the camera frame, per frame
    opening = float(np.degrees(np.arccos(np.clip(-up[:, 2], -1, 1))).min())
    bottom = float(np.degrees(np.arccos(np.clip(up[:, 2], -1, 1))).min())

    surface, normals = _surface_samples(mesh, samples, seed)
    closest = o3d.t.geometry.RaycastingScene()
    closest.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)), o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    frames = len(trajectory)
    hand_obj: list[np.ndarray] = []  # per frame: hand mesh (vertices in the object frame, faces)
    for i in range(frames):  # a few hundred triangles per frame
        T = trajectory.pose(i)
        part = hand_parts(hands[i], T, elbow_at(layout, T[:3, 3]))
        hand_obj.append((part.vertices - T[:3, 3]) @ T[:3, :3])
    faces_hand = hand_parts(hands[0], trajectory.pose(0), elbow_at(layout, trajectory.positions[0])).faces
    grasp_of = np.array([h.grasp if h.holding else -1 for h in hands])
    grasps = sorted(set(grasp_of[grasp_of >= 0].tolist()))

    patches, spaces = {}, {}
    for g in grasps:
        i = int(np.flatnonzero(grasp_of == g)[0])  # the grasp is fixed in the object frame while held
        vertices = hand_obj[i]
        # the palm, fingers and thumb only: the forearm's far end is not on the object
        # (a point closer than a few millimetres to the surface lies in the surface's own voxels: never "free")
        gap = closest.compute_distance(o3d.core.Tensor(vertices.astype(np.float32))).numpy()
        near_hand = (gap > HAND_SPACE[0]) & (gap < HAND_SPACE[1])
        hand_scene = o3d.t.geometry.RaycastingScene()
        hand_scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces_hand.astype(np.uint32)))
        answer = hand_scene.compute_closest_points(o3d.core.Tensor(surface.astype(np.float32)))
        to_hand = answer["points"].numpy().astype(np.float64) - surface
        # near the hand and on its side of the surface (not a thin wall's far face, inside a mug)
        patches[g] = np.flatnonzero((np.linalg.norm(to_hand, axis=1) < CONTACT) & (np.einsum("ij,ij->i", to_hand, normals) > 0))
        spaces[g] = vertices[near_hand]

    seen = {g: np.zeros(len(patches[g]), bool) for g in grasps}
    free = {g: np.zeros(len(spaces[g]), bool) for g in grasps}
    object_faces = np.asarray(mesh.faces)
    ever = np.zeros(len(surface), bool)
    for i in range(frames):
        T = trajectory.pose(i)
        arm = upper_arm_part(layout, elbow_at(layout, T[:3, 3]))
        hand_cam = hand_obj[i] @ T[:3, :3].T + T[:3, 3]
        vertices = np.concatenate([np.asarray(mesh.vertices) @ T[:3, :3].T + T[:3, 3], hand_cam, arm.vertices])
        faces = np.concatenate([object_faces, faces_hand + len(mesh.vertices), arm.faces + len(mesh.vertices) + len(hand_cam)])
        points = surface @ T[:3, :3].T + T[:3, 3]
        t, length = _first_hits(vertices, faces, points)
        facing = -np.einsum("ij,ij->i", normals @ T[:3, :3].T, points / length[:, None])
        ever |= (np.abs(t - length) < MARGIN) & (facing > np.cos(np.radians(SEEN_INCIDENCE)))
        for g in grasps:
            if grasp_of[i] >= 0 and grasp_of[i] != g:  # held by another grasp: is g's patch in view?
                points = surface[patches[g]] @ T[:3, :3].T + T[:3, 3]
                t, length = _first_hits(vertices, faces, points)
                facing = -np.einsum("ij,ij->i", normals[patches[g]] @ T[:3, :3].T, points / length[:, None])
                seen[g] |= (np.abs(t - length) < MARGIN) & (facing > np.cos(np.radians(SEEN_INCIDENCE)))
            if grasp_of[i] != g and len(spaces[g]):  # the hand is elsewhere (or moving): is its old space seen free?
                points = spaces[g] @ T[:3, :3].T + T[:3, 3]
                t, length = _first_hits(vertices, faces, points)
                free[g] |= t > length + MARGIN
    share = lambda flags: float(flags.mean()) if len(flags) else 1.0  # noqa: E731
    return Coverage(opening, bottom, [share(seen[g]) for g in grasps], [share(free[g]) for g in grasps], float(1.0 - ever.mean()))
