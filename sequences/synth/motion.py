"""The object's hand-held trajectory and the hand's grasps, over the frames of a sequence.

The object (ShapeNet frame) is carried through all orientations, as an annotator shows an object
for reconstruction: its y axis starts pointing up (camera -y), then alternately to a side and
down (camera +y) or up. The first two side keys point it toward the camera (within ~15 degrees:
a view into a mug's or bowl's opening) and away from it (the bottom), in random order; later side
keys are random (camera +-x, toward or away). Random spins about the object's own axis (the best
of a few draws at turning each of its six faces toward the camera: tilting alone never turns the
sides along camera x to it). A C2 rotation spline interpolates the keys (about 90-100 degrees per
key, one key every ~22 frames: 5-7 degrees per frame while held, a quarter of that while the hand
regrasps). Its centre drifts smoothly 0.5-0.85 m in front of the camera.

A hand holds the object by a grasp fixed in the object frame (palm on the surface, fingers wrapped
on it), releases it, moves around it and grasps elsewhere (at least one regrasp per sequence).
Each grasp is placed so that the space its hand fills next to the surface (its mesh HAND_SPACE off
the surface) is seen free, in front of the object and of the other grasps' hands, in frames held by
another grasp or resting on a table: the hand never hides for good what only its hold could show.
That is a requirement (all but HIDDEN_TOLERANCE of the space), not a preference: the grasps are
planned in turn, then planned again against all the others' hands (:mod:`.coverage` measures it).
Frames: camera OpenCV (x right, y down, z forward), metres; poses map object to camera.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial.transform import Rotation, RotationSpline

from .primitives import Part

#: Frames per 90-degree key of the orientation path (about 5 degrees per frame).
FRAMES_PER_KEY = 22
#: Frames per grasp before the hand regrasps.
FRAMES_PER_GRASP = 45
#: The hand's space next to the surface: points of the hand's mesh this far off it (metres). Nearer, a point lies in
#: the surface's own voxels and is never "free"; farther, it is no imprint a carving could keep.
HAND_SPACE = (0.004, 0.012)
#: How many of the best-scored contacts are wrapped and checked at a time, and the weight of the share of their
#: hand's space never seen free in a frame of another grasp.
CANDIDATES = 24
HIDDEN_WEIGHT = 8.0
#: The share of a grasp's hand space that may stay unseen free: a grasp above it is taken only where no contact
#: of the object does better (a regrasp exists so that a reconstruction can see where the hand was).
HIDDEN_TOLERANCE = 0.02
#: At most this many points of a hand's space are checked (evenly strided).
SPACE_POINTS = 300
#: Radius (metres) of the palm's patch of surface, and the angle (degrees) within which a surface faces the camera.
PATCH = 0.025
SHOWN_INCIDENCE = 70.0
#: Hand dimensions, metres: palm semi-axes (across, along the fingers, thickness), finger and thumb radii.
PALM = np.array([0.042, 0.046, 0.013])
FINGER_RADIUS = 0.0085
THUMB_RADIUS = 0.0100
FOREARM_RADIUS = 0.030
#: Wrist in the hand frame (behind the palm, opposite the fingers).
WRIST = np.array([0.0, -0.060, 0.006])
RETRACT = 0.05  # how far the open hand backs off the surface between grasps, metres


@dataclass
class Trajectory:
    """Object-to-camera rotations (N, 3, 3) and positions (N, 3) of the object's box centre, one per frame."""

    rotations: np.ndarray
    positions: np.ndarray

    def pose(self, i: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.rotations[i]
        T[:3, 3] = self.positions[i]
        return T

    def pose_at(self, t: float) -> np.ndarray:
        """The pose at fractional frame ``t`` (a depth image taken between two colour frames): rotation slerped and
        position interpolated between the neighbouring frames, extrapolated by the last (first) step beyond the ends."""
        n = len(self)
        if n == 1:
            return self.pose(0)
        i = int(np.clip(np.floor(t), 0, n - 2))
        u = float(t - i)
        step = Rotation.from_matrix(self.rotations[i + 1] @ self.rotations[i].T).as_rotvec()
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(step * u).as_matrix() @ self.rotations[i]
        T[:3, 3] = self.positions[i] + u * (self.positions[i + 1] - self.positions[i])
        return T

    def __len__(self) -> int:
        return len(self.positions)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _align(a: np.ndarray, b: np.ndarray) -> Rotation:
    """The smallest rotation taking unit vector a to unit vector b."""
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-9:
        if c > 0:
            return Rotation.identity()
        other = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 0, 1.0])
        return Rotation.from_rotvec(_unit(np.cross(a, other)) * np.pi)
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c))


#: Standard deviation of the random tilt of a key's y direction (per component, before normalising):
#: toward / away keys (within ~15 degrees of the camera axis), the others.
KEY_NOISE = (0.06, 0.2)
#: Range (radians, either sense) of the random spin about the object's own y axis at each key, and how many
#: sets of spins are drawn to choose from.
SPIN = 1.4
SPIN_DRAWS = 24
#: How fast the object moves while the hand is off it (regrasping), relative to while it is held.
RELEASED_SPEED = 0.25


def _key_rotations(start: Rotation, targets: list[np.ndarray], spins: np.ndarray) -> list[Rotation]:
    """Key orientations: from ``start``, each spins the object about its own y axis (``spins``, radians), then
    turns its y axis onto the next target (smallest rotation)."""
    rotations = [start]
    for target, spin in zip(targets, spins):
        previous = rotations[-1]
        rotations.append(_align(previous.apply([0.0, 1.0, 0.0]), target) * previous * Rotation.from_rotvec([0.0, spin, 0.0]))
    return rotations


def _worst_face(rotations: list[Rotation]) -> float:
    """Of the object's six face directions (+-x, +-y, +-z), the largest of their smallest angles (degrees) to the
    direction toward the camera (camera -z) along the keys, slerped between them (8 steps a key)."""
    steps = np.linspace(0.0, 1.0, 8, endpoint=False)[:, None]
    path = [a * Rotation.from_rotvec((a.inv() * b).as_rotvec()[None] * steps) for a, b in zip(rotations[:-1], rotations[1:])]
    R = Rotation.concatenate(path).as_matrix()  # (S, 3, 3); row 2 holds the axes' camera z components
    toward = np.concatenate([-R[:, 2, :], R[:, 2, :]], axis=1)  # (S, 6): cosines of +-x, +-y, +-z to camera -z
    return float(np.degrees(np.arccos(np.clip(toward.max(axis=0), -1, 1))).max())


def object_trajectory(frames: int, rng: np.random.Generator, held: np.ndarray | None = None, turn_speed: float = 1.0) -> Trajectory:
    """A smooth hand-held trajectory visiting up, down and sideways orientations of the object's y axis,
    including toward the camera (into the top) and away from it (the bottom) whenever it has 4+ keys (always).

    ``held`` (frames,) bool: frames where the hand holds the object; in the others (a regrasp) the
    object drifts at RELEASED_SPEED of its pace instead of turning on its own. ``turn_speed`` scales the
    number of keys (about 90 degrees each) over the frames.
    """
    keys = max(4, int(round(frames * turn_speed / FRAMES_PER_KEY)))
    up, down = np.array([0.0, -1.0, 0.0]), np.array([0.0, 1.0, 0.0])
    sides = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, -1.0], [0, 0, 1.0]])
    # upright, handle (object -z) toward the camera, then a random spin about the object's y axis
    start = Rotation.from_matrix(np.diag([-1.0, -1.0, 1.0])) * Rotation.from_rotvec([0, rng.uniform(-np.pi, np.pi), 0])
    start = Rotation.from_rotvec(rng.normal(0, 0.15, 3)) * start
    # the first two side keys look into the object's top (y toward the camera: a mug's or bowl's inside)
    # and at its bottom (y away from it), in random order and with little noise; later sides are random
    toward, away = np.array([0.0, 0, -1.0]), np.array([0.0, 0, 1.0])
    shown = [toward, away] if rng.random() < 0.5 else [away, toward]
    targets = []
    for k in range(1, keys + 1):
        if k % 2:
            target = shown[k // 2] if k // 2 < len(shown) else sides[rng.integers(len(sides))]
            noise = KEY_NOISE[0] if k // 2 < len(shown) else KEY_NOISE[1]
        else:
            target = down if (k // 2) % 2 else up
            noise = KEY_NOISE[1]
        targets.append(_unit(target + rng.normal(0, noise, 3)))
    # random spins about the object's own y axis: of a few draws, the one that turns every face of the object
    # (+-x, +-y, +-z) most squarely toward the camera at some point (tilting the y axis toward and away from the
    # camera alone never turns the faces along camera x to it)
    draws = [_key_rotations(start, targets, rng.uniform(-SPIN, SPIN, keys)) for _ in range(SPIN_DRAWS)]
    rotations = min(draws, key=_worst_face)
    times = np.linspace(0.0, 1.0, keys + 1)
    times[1:-1] += rng.uniform(-0.25, 0.25, keys - 1) / keys
    # path parameter per frame: even steps, slowed where the object is not held (smoothed to stay C1)
    pace = np.ones(frames) if held is None else np.where(held, 1.0, RELEASED_SPEED)
    pace = np.convolve(np.pad(pace, 2, mode="edge"), np.ones(5) / 5, mode="valid")
    s = np.concatenate([[0.0], np.cumsum((pace[1:] + pace[:-1]) / 2)]) if frames > 1 else np.zeros(1)
    s = s / s[-1] if frames > 1 else s
    R = RotationSpline(times, Rotation.concatenate(rotations))(s).as_matrix()

    return Trajectory(R, drift_positions(s, keys, rng))


def drift_positions(s: np.ndarray, keys: int, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) box centres along path parameters ``s`` in 0..1: a base point plus two sinusoids per axis (more cycles
    with more ``keys``); the amplitudes keep the object 0.5-0.85 m away and in view."""
    base = np.array([rng.uniform(-0.04, 0.04), rng.uniform(-0.03, 0.04), rng.uniform(0.58, 0.74)])
    amplitude = np.array([0.05, 0.035, 0.08])
    cycles = max(1.0, keys / 4)
    phase = rng.uniform(0, 2 * np.pi, (2, 3))
    freq = rng.uniform(0.5, 1.0, (2, 3)) * cycles
    offset = 0.6 * np.sin(2 * np.pi * freq[0] * s[:, None] + phase[0]) + 0.4 * np.sin(2 * np.pi * freq[1] * s[:, None] + phase[1])
    return base + amplitude * offset


@dataclass
class Grasp:
    """A grasp: the hand frame in the object frame and the finger chains (wrapped on the surface) in the hand frame.

    Hand frame: origin at the palm centre, +y along the fingers, +z out of the back of the hand
    (the palm's inside touches the object at z = -PALM[2]).
    """

    contact: np.ndarray  # (3,) object frame
    hand_in_object: np.ndarray  # (4, 4)
    wrapped: np.ndarray  # (5, 4, 3) chains in the hand frame: 4 fingers + thumb, 4 joints each
    first: int  # first frame held
    last: int  # last frame held


def open_hand() -> np.ndarray:
    """(5, 4, 3) finger chains of a relaxed open hand in the hand frame (fingers slightly curled)."""
    offsets = np.array([0.030, 0.010, -0.010, -0.030])  # across the palm
    lengths = np.array([0.075, 0.082, 0.077, 0.062])
    steps = np.array([0.0, 0.45, 0.75, 1.0])
    along = PALM[1] * 0.85 + lengths[:, None] * steps[None]
    curl = -0.25 * (along - along[:, :1])
    fingers = np.stack([np.broadcast_to(offsets[:, None], along.shape), along, curl - 0.004], -1)
    thumb_dir = _unit(np.array([-0.75, 0.55, -0.35]))
    thumb = np.array([-PALM[0] * 0.9, -0.01, -0.006]) + np.array([0.0, 0.035, 0.062, 0.085])[:, None] * thumb_dir
    return np.concatenate([fingers, thumb[None]], axis=0)


@dataclass
class View:
    """Frames that show the object while a grasp is elsewhere: the object's rotations (M, 3, 3) and positions (M, 3)
    in the camera frame, and the hand that holds it then (object frame; None: no hand, or not yet planned)."""

    rotations: np.ndarray
    positions: np.ndarray
    hand: Part | None = None


class GraspPlanner:
    """Chooses grasp points on the object's surface and wraps the fingers on it (closest-point queries)."""

    def __init__(self, mesh: trimesh.Trimesh, rng: np.random.Generator, hand: Callable[[Grasp], Part]) -> None:
        """``hand(grasp)``: the mesh of the hand holding ``grasp`` (palm, fingers, thumb), object frame."""
        self.mesh = mesh
        self.rng = rng
        self.hand = hand
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)), o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
        # area-weighted surface samples with their face normals (seeded, so grasps are deterministic)
        area = np.asarray(mesh.area_faces, dtype=np.float64)
        face = rng.choice(len(area), size=600, p=area / area.sum())
        uv = rng.random((600, 2))
        flip = uv.sum(1) > 1
        uv[flip] = 1 - uv[flip]
        tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[face]]
        self.samples = tri[:, 0] + uv[:, :1] * (tri[:, 1] - tri[:, 0]) + uv[:, 1:] * (tri[:, 2] - tri[:, 0])
        normals = np.asarray(mesh.face_normals)[face]
        # a palm needs open space in front of it: reject points inside a cavity (a mug's inside) and turn
        # normals that point into the object (scanned meshes wind their faces either way)
        ahead = self._blocked(self.samples, normals)
        behind = self._blocked(self.samples, -normals)
        flip = ahead & ~behind
        normals[flip] *= -1.0
        self.sample_normals = normals
        self.open = ~(ahead & behind)
        self.diagonal = float(np.linalg.norm(mesh.extents))

    def _blocked(self, points: np.ndarray, directions: np.ndarray, reach: float = 0.12) -> np.ndarray:
        """Whether a ray from just off each point along its direction meets the object within ``reach`` metres."""
        rays = np.concatenate([points + directions * 1e-3, directions], axis=1).astype(np.float32)
        return self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() < reach

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest surface points (N, 3) and their face normals (N, 3), object frame."""
        answer = self.scene.compute_closest_points(o3d.core.Tensor(np.asarray(points, np.float32)))
        return answer["points"].numpy().astype(np.float64), answer["primitive_normals"].numpy().astype(np.float64)

    def plan(self, rotations: np.ndarray, positions: np.ndarray, elbow: np.ndarray, avoid: list[np.ndarray], first: int, last: int,
             elsewhere: list[View] | None = None) -> Grasp:
        """A grasp held over frames first..last, given the object's rotations (K, 3, 3) and positions (K, 3) over them.

        The palm goes where, through the whole hold, the surface faces sideways toward the elbow
        and never the camera (so the forearm reaches it from behind or the side and the fingers
        wrap over the front), away from earlier contacts in ``avoid``, and where the surface faces
        the camera in some frame held by another grasp (``elsewhere``: those frames, with the other
        grasp's hand where it is known), so what this hand covers is shown free then.
        """
        middle = len(rotations) // 2
        to_elbow = _unit(elbow - positions)  # (K, 3)
        view = _unit(positions)
        lateral = _unit(to_elbow - np.einsum("kj,kj->k", to_elbow, view)[:, None] * view)
        normals = _unit(self.sample_normals)
        # per candidate: fingers wrap around the object's y axis when the palm is on the side, else across x;
        # the wrist (behind the fingers) points toward the elbow at the middle of the hold
        around = np.where(np.abs(normals[:, 1:2]) < 0.85, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
        fingers = _unit(np.cross(normals, around))
        fingers *= np.where((fingers @ rotations[middle].T) @ to_elbow[middle] > 0, -1.0, 1.0)[:, None]
        wrist = self.samples + normals * PALM[2] + fingers * WRIST[1]
        normals_cam = np.einsum("kij,nj->kni", rotations, normals)  # (K, N, 3)
        toward_elbow = np.einsum("kni,ki->kn", normals_cam, lateral)
        along_view = np.einsum("kni,ki->kn", normals_cam, view)  # > 0: faces away from the camera
        wrist_behind = np.einsum("kij,nj->kni", rotations, wrist) @ np.array([0.0, 0.0, 1.0])  # wrist depth minus centre depth
        score = (toward_elbow - 1.5 * np.abs(along_view - 0.25)).mean(axis=0)
        score -= 2.0 * np.clip(-along_view - 0.2, 0, None).max(axis=0)  # the palm never faces the camera
        score -= 4.0 * np.clip(-wrist_behind / 0.05, 0, None).max(axis=0)  # nor does the wrist come in front (the forearm would hide all)
        score = score + self.rng.uniform(0.0, 0.3, len(self.samples)) - 5.0 * ~self.open
        for previous in avoid:  # a regrasp takes the object elsewhere, whatever else the score says
            near = np.linalg.norm(self.samples - previous, axis=1) < 0.45 * self.diagonal
            score = score - 20.0 * near
        order = np.argsort(-score)
        if not elsewhere:
            pick = int(order[0])
            return self._grasp(self.samples[pick], normals[pick], fingers[pick], first, last)
        # the best-scored candidate whose hand leaves at most HIDDEN_TOLERANCE of the space it fills next to the
        # surface never seen free (in front of the object and the other hands) in a frame held by another grasp, and
        # whose palm patch faces the camera, unhidden by the object, in such a frame: a regrasp must take the hand off
        # what only those frames can show, or a carving keeps the hand's imprint. Failing that, the least hidden.
        shown = self.shown(np.concatenate([v.rotations for v in elsewhere]), np.concatenate([v.positions for v in elsewhere]))
        scenes = self._scenes(elsewhere)
        kept, kept_total, least, least_key = None, -np.inf, None, (np.inf, 0.0)
        for start in range(0, len(order), CANDIDATES):
            for pick in order[start : start + CANDIDATES]:  # a few closest-point queries and ray casts each
                grasp = self._grasp(self.samples[pick], normals[pick], fingers[pick], first, last)
                hidden = self._hidden(grasp, elsewhere, scenes)
                patch = (np.linalg.norm(self.samples - self.samples[pick], axis=1) < PATCH) & (normals @ normals[pick] > 0.5)
                total = score[pick] - HIDDEN_WEIGHT * (hidden + 1.0 - shown[patch].mean())
                if hidden <= HIDDEN_TOLERANCE and total > kept_total:
                    kept, kept_total = grasp, total
                if (hidden, -total) < least_key:
                    least, least_key = grasp, (hidden, -total)
            if kept is not None:
                return kept
        return least

    def hidden(self, grasp: Grasp, elsewhere: list[View]) -> float:
        """The share of ``grasp``'s hand space that no frame of ``elsewhere`` sees free."""
        return self._hidden(grasp, elsewhere, self._scenes(elsewhere))

    def _scenes(self, elsewhere: list[View]) -> list[o3d.t.geometry.RaycastingScene]:
        """A ray-casting scene per view group: the object, and the other grasp's hand where it is known."""
        scenes = []
        for v in elsewhere:  # a few groups
            if v.hand is None:
                scenes.append(self.scene)
                continue
            scene = o3d.t.geometry.RaycastingScene()
            for vertices, faces in ((self.mesh.vertices, self.mesh.faces), (v.hand.vertices, v.hand.faces)):
                scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)), o3d.core.Tensor(np.asarray(faces, np.uint32)))
            scenes.append(scene)
        return scenes

    def _hidden(self, grasp: Grasp, elsewhere: list[View], scenes: list[o3d.t.geometry.RaycastingScene]) -> float:
        space = self.hand_space(grasp)
        if not len(space):
            return 0.0
        free = np.zeros(len(space), bool)
        for v, scene in zip(elsewhere, scenes):
            free |= self.seen_free(space, v.rotations, v.positions, scene)
        return 1.0 - float(free.mean())

    def hand_space(self, grasp: Grasp) -> np.ndarray:
        """(P, 3) points of the grasp's hand mesh HAND_SPACE off the surface (at most about SPACE_POINTS), object frame."""
        vertices = self.hand(grasp).vertices
        gap = self.scene.compute_distance(o3d.core.Tensor(vertices.astype(np.float32))).numpy()
        space = vertices[(gap > HAND_SPACE[0]) & (gap < HAND_SPACE[1])]
        return space[:: max(1, len(space) // SPACE_POINTS)]

    def shown(self, rotations: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """(N,) bool: whether some frame shows each surface sample: facing the camera within SHOWN_INCIDENCE, unhidden by the object."""
        centres = -np.einsum("mji,mj->mi", rotations, positions)  # camera centres in the object frame (M, 3)
        back = centres[:, None] - self.samples[None]  # (M, N, 3) from each sample toward the camera
        length = np.linalg.norm(back, axis=2)
        back /= length[..., None]
        facing = np.einsum("mnj,nj->mn", back, self.sample_normals) > np.cos(np.radians(SHOWN_INCIDENCE))
        rays = np.concatenate([np.broadcast_to(self.samples + self.sample_normals * 1e-3, back.shape), back], axis=2).reshape(-1, 6)
        t = self.scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy().reshape(length.shape)
        return (facing & (t > length)).any(axis=0)

    def seen_free(self, points: np.ndarray, rotations: np.ndarray, positions: np.ndarray,
                  scene: o3d.t.geometry.RaycastingScene | None = None) -> np.ndarray:
        """(P,) bool: whether some frame (object rotations (M, 3, 3), positions (M, 3)) sees each point (object frame)
        in front of the object (or of ``scene``, in the object frame): the ray from the camera through it meets the
        surface only beyond it (or never)."""
        if not len(rotations):
            return np.zeros(len(points), bool)
        centres = -np.einsum("mji,mj->mi", rotations, positions)  # camera centres in the object frame (M, 3)
        ray = points[None] - centres[:, None]  # (M, P, 3)
        length = np.linalg.norm(ray, axis=2)
        rays = np.concatenate([np.broadcast_to(centres[:, None], ray.shape), ray / length[..., None]], axis=2).reshape(-1, 6)
        t = (self.scene if scene is None else scene).cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy().reshape(length.shape)
        return (t > length + 0.002).any(axis=0)

    def _grasp(self, contact: np.ndarray, normal: np.ndarray, fingers: np.ndarray, first: int, last: int) -> Grasp:
        """The grasp with its palm on ``contact`` (outward ``normal``), fingers along ``fingers``, wrapped on the surface."""
        across = np.cross(fingers, normal)
        T = np.eye(4)
        T[:3, :3] = np.stack([across, fingers, normal], axis=1)
        T[:3, 3] = contact + normal * PALM[2]
        chains = open_hand()
        radius = np.array([FINGER_RADIUS] * 4 + [THUMB_RADIUS])[:, None, None]
        points_obj = chains.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
        near, near_n = self.closest(points_obj)
        # a scanned mesh's zero-area triangles have no normal: there, the way from the surface to the joint
        length = np.linalg.norm(near_n, axis=1, keepdims=True)
        near_n = np.where(length > 1e-12, near_n / np.maximum(length, 1e-12), _unit(points_obj - near + 1e-12))
        # keep the outward side: a normal facing away from the query point belongs to the far wall
        facing = np.sign(np.einsum("ij,ij->i", points_obj - near, near_n))
        facing[facing == 0] = 1.0
        wrapped_obj = near.reshape(5, 4, 3) + (near_n * facing[:, None]).reshape(5, 4, 3) * radius
        wrapped = (wrapped_obj.reshape(-1, 3) - T[:3, 3]) @ T[:3, :3]
        # the finger bases stay on the palm edge: only the joints beyond them wrap
        wrapped = wrapped.reshape(5, 4, 3)
        wrapped[:, 0] = chains[:, 0]
        return Grasp(contact, T, wrapped, first, last)


@dataclass
class HandState:
    """The hand at one frame: its frame in the object frame, finger chains in the hand frame, whether it holds the
    object, and whether it is in the scene at all (it is not while the object rests on a table)."""

    hand_in_object: np.ndarray  # (4, 4)
    chains: np.ndarray  # (5, 4, 3)
    holding: bool
    grasp: int  # index of the current (or, while moving, the next) grasp
    present: bool = True


def _smoothstep(x: np.ndarray | float) -> np.ndarray | float:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _offset(T: np.ndarray, distance: float) -> np.ndarray:
    out = T.copy()
    out[:3, 3] += T[:3, 2] * distance  # back off along the hand's +z (out of the surface)
    return out


def _interpolate(A: np.ndarray, B: np.ndarray, u: float) -> np.ndarray:
    """Hand frame between A and B: rotation by slerp, position around the object (not through it)."""
    rot = Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]]))
    R = (rot[0] * Rotation.from_rotvec((rot[0].inv() * rot[1]).as_rotvec() * u)).as_matrix()
    a, b = A[:3, 3], B[:3, 3]
    ra, rb = np.linalg.norm(a), np.linalg.norm(b)
    da, db = a / ra, b / rb
    angle = np.arccos(np.clip(da @ db, -1, 1))
    if angle < 1e-6:
        direction = da
    elif angle > np.pi - 1e-3:  # opposite sides: go around through any perpendicular
        perpendicular = _unit(np.cross(da, [0.0, 1.0, 0.0] if abs(da[1]) < 0.9 else [1.0, 0.0, 0.0]))
        direction = np.cos(angle * u) * da + np.sin(angle * u) * perpendicular
    else:
        direction = (np.sin((1 - u) * angle) * da + np.sin(u * angle) * db) / np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = direction * ((1 - u) * ra + u * rb)
    return T


def grasp_schedule(frames: int) -> list[tuple[int, int]]:
    """The frames (first, last) of each grasp: one per ~FRAMES_PER_GRASP frames, at least two (one regrasp).

    Between grasps a window of frames (30% of a grasp period, at least one frame; about 0.3-0.5 s)
    has the hand releasing, moving and re-approaching.
    """
    count = max(2, 1 + frames // FRAMES_PER_GRASP)
    window = max(1, int(round(0.3 * frames / count)))
    edges = np.linspace(0, frames, count + 1)
    schedule = []
    for k in range(count):
        first = 0 if k == 0 else int(round(edges[k])) + window // 2 + window % 2
        last = frames - 1 if k == count - 1 else int(round(edges[k + 1])) - window // 2 - 1
        first, last = min(first, frames - 1), max(min(last, frames - 1), min(first, frames - 1))
        schedule.append((first, last))
    return schedule


def held_frames(frames: int, schedule: list[tuple[int, int]]) -> np.ndarray:
    """(frames,) bool: whether the hand holds the object in each frame."""
    held = np.zeros(frames, dtype=bool)
    for first, last in schedule:  # a few grasps
        held[first : last + 1] = True
    return held


def plan_grasps(schedule: list[tuple[int, int]], trajectory: Trajectory, planner: GraspPlanner, elbow: np.ndarray,
                resting: np.ndarray | None = None) -> list[Grasp]:
    """A grasp for each (first, last) frame range of ``schedule``, each elsewhere than the one before.

    ``resting`` (frames,) bool: frames where the object rests with no hand on it; they show it free too.
    Each grasp is planned against the hands of the grasps before it; then every grasp whose hand space the
    other grasps' hands leave hidden beyond HIDDEN_TOLERANCE is planned again against all of them (twice over).
    """
    holder = np.full(len(trajectory), -1)
    for k, (first, last) in enumerate(schedule):  # a few grasps
        holder[first : last + 1] = k
    shows = holder >= 0
    if resting is not None:
        shows |= resting

    def elsewhere(k: int, grasps: list[Grasp]) -> list[View]:
        views = []
        for j in range(-1, len(schedule)):  # the frames of each other grasp, and those with none
            frames = shows & (holder == j)
            if j != k and frames.any():
                views.append(View(trajectory.rotations[frames], trajectory.positions[frames], planner.hand(grasps[j]) if 0 <= j < len(grasps) else None))
        return views

    def plan(k: int, views: list[View], avoid: list[np.ndarray]) -> Grasp:
        first, last = schedule[k]
        hold = slice(first, last + 1)
        return planner.plan(trajectory.rotations[hold], trajectory.positions[hold], elbow, avoid, first, last, views)

    grasps: list[Grasp] = []
    for k in range(len(schedule)):
        grasps.append(plan(k, elsewhere(k, grasps), [g.contact for g in grasps]))
    for _ in range(2):
        for k in range(len(schedule)):
            views = elsewhere(k, grasps)
            if planner.hidden(grasps[k], views) > HIDDEN_TOLERANCE:
                grasps[k] = plan(k, views, [g.contact for j, g in enumerate(grasps) if j != k])
    return grasps


#: Frames over which the hand comes to (or leaves) an object resting on a table, and how far away it starts (metres).
APPROACH_FRAMES = 5
AWAY = 0.3


def _approach(grasp: Grasp, frames_left: int, relaxed: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """The hand ``frames_left`` frames before it takes ``grasp`` (or after it lets go) of a resting object:
    from AWAY off the surface to the grasp, opening as it leaves; absent beyond APPROACH_FRAMES."""
    if frames_left > APPROACH_FRAMES:
        return grasp.hand_in_object, relaxed, False
    u = _smoothstep(frames_left / APPROACH_FRAMES)
    return _offset(grasp.hand_in_object, RETRACT * min(1.0, 3 * u) + AWAY * u), (1 - u) * grasp.wrapped + u * relaxed, True


def hand_states(frames: int, grasps: list[Grasp], resting: np.ndarray | None = None) -> list[HandState]:
    """The hand at every frame: holding within a grasp, else releasing / moving / re-approaching; with ``resting``
    (frames,) bool, it leaves a resting object and comes back to it (absent in between), as before a first grasp."""
    relaxed = open_hand()
    states = []
    for i in range(frames):  # per frame, a handful of 4x4 operations
        current = next((k for k, g in enumerate(grasps) if g.first <= i <= g.last), None)
        if current is not None:
            g = grasps[current]
            states.append(HandState(g.hand_in_object, g.wrapped, True, current))
            continue
        after = next((k for k, g in enumerate(grasps) if g.first > i), None)
        if after is None or after == 0 or (resting is not None and resting[i]):
            # a resting object: the hand comes to the next grasp, or leaves the last one, from far off
            before = next((k for k in range(len(grasps) - 1, -1, -1) if grasps[k].last < i), None)
            to_next = grasps[after].first - i if after is not None else frames
            from_last = i - grasps[before].last if before is not None else frames
            k = after if to_next <= from_last else before
            T, chains, present = _approach(grasps[k], min(to_next, from_last), relaxed)
            states.append(HandState(T, chains, False, k if after is None else after, present))
            continue
        A, B = grasps[after - 1], grasps[after]
        u = (i - A.last) / (B.first - A.last)
        if u < 0.35:
            opening = _smoothstep(u / 0.35)
            T = _offset(A.hand_in_object, RETRACT * opening)
            chains = (1 - opening) * A.wrapped + opening * relaxed
        elif u > 0.65:
            closing = _smoothstep((1 - u) / 0.35)
            T = _offset(B.hand_in_object, RETRACT * closing)
            chains = (1 - closing) * B.wrapped + closing * relaxed
        else:
            T = _interpolate(_offset(A.hand_in_object, RETRACT), _offset(B.hand_in_object, RETRACT), _smoothstep((u - 0.35) / 0.3))
            chains = relaxed
        states.append(HandState(T, chains, False, after))
    return states
