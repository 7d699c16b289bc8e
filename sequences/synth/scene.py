"""The scene around the object: the hand (palm, fingers, forearm), the person holding it, a wall and a table.

Everything is in the camera frame (OpenCV: x right, y down, z forward), metres. The layout (where
the person stands, the wall's distance and tilt, the table's height, colours, the light) is drawn
once per sequence; :func:`frame_parts` builds the triangle meshes of one frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .motion import FINGER_RADIUS, FOREARM_RADIUS, PALM, THUMB_RADIUS, WRIST, Grasp, HandState
from .primitives import Part, capsules, concatenate, ellipsoids, quad

# Scene labels (per triangle; 0 = nothing hit)
OBJECT, HAND, PERSON, WALL, TABLE = 1, 2, 3, 4, 5
LABEL_NAMES = {OBJECT: "object", HAND: "hand", PERSON: "person", WALL: "wall", TABLE: "table"}


@dataclass
class Layout:
    """Per-sequence scene layout and appearance (camera frame, metres; colours RGB in 0..1)."""

    side: float  # -1: the holding arm is on the image's left, +1: right
    torso_centre: np.ndarray
    torso_axes: np.ndarray  # semi-axes x, y, z
    head_centre: np.ndarray
    head_radius: float
    shoulder: np.ndarray
    elbow: np.ndarray  # at the object's mean position; moves with the object
    mean_position: np.ndarray  # the object's mean position
    wall_centre: np.ndarray
    wall_normal: np.ndarray  # toward the camera
    table_height: float  # camera y of the table top
    table_near: float  # camera z of the table's front edge
    skin: np.ndarray
    shirt: np.ndarray
    hair: np.ndarray
    wall_colour: np.ndarray
    table_colour: np.ndarray
    posters: np.ndarray  # (P, 7): centre x, y, half width, half height, r, g, b (on the wall, camera x/y)
    light: np.ndarray  # unit direction toward the light


def make_layout(mean_position: np.ndarray, rng: np.random.Generator, table: tuple[float, float] | None = None) -> Layout:
    """A random but plausible layout for an object held around ``mean_position``; ``table`` (the top's camera y and
    the camera z of its front edge) places the table where the object rests on it."""
    side = float(rng.choice([-1.0, 1.0]))
    torso_z = mean_position[2] + rng.uniform(0.38, 0.5)
    torso_centre = np.array([rng.uniform(-0.08, 0.08), rng.uniform(0.22, 0.3), torso_z])
    torso_axes = np.array([rng.uniform(0.17, 0.21), rng.uniform(0.3, 0.36), rng.uniform(0.1, 0.13)])
    head_radius = rng.uniform(0.085, 0.1)
    head_centre = torso_centre + np.array([rng.uniform(-0.02, 0.02), -torso_axes[1] - head_radius - 0.03, 0.0])
    shoulder = torso_centre + np.array([side * torso_axes[0] * 0.95, -torso_axes[1] * 0.8, -0.02])
    elbow = np.array([side * rng.uniform(0.14, 0.2) + mean_position[0], mean_position[1] + rng.uniform(0.12, 0.2), mean_position[2] + rng.uniform(0.22, 0.3)])
    wall_z = torso_z + rng.uniform(0.6, 1.2)
    yaw = rng.uniform(-0.2, 0.2)
    wall_normal = np.array([np.sin(yaw), 0.0, -np.cos(yaw)])
    hue = rng.uniform(0, 1, 3)
    posters = np.column_stack([
        rng.uniform(-1.0, 1.0, 3), rng.uniform(-0.8, 0.2, 3), rng.uniform(0.1, 0.3, 3), rng.uniform(0.1, 0.3, 3), rng.uniform(0.1, 0.9, (3, 3)),
    ])
    light = np.array([rng.uniform(-0.6, 0.2), rng.uniform(-0.9, -0.4), -1.0])
    return Layout(
        side=side, torso_centre=torso_centre, torso_axes=torso_axes, head_centre=head_centre, head_radius=head_radius,
        shoulder=shoulder, elbow=elbow, mean_position=np.asarray(mean_position, float),
        wall_centre=np.array([0.0, 0.0, wall_z]), wall_normal=wall_normal,
        table_height=rng.uniform(0.3, 0.42) if table is None else table[0],
        table_near=mean_position[2] + rng.uniform(0.1, 0.2) if table is None else table[1],
        skin=np.array([0.86, 0.63, 0.5]) * rng.uniform(0.6, 1.1) + rng.uniform(-0.04, 0.04, 3),
        shirt=0.15 + 0.7 * hue, hair=np.array([0.12, 0.08, 0.05]) * rng.uniform(0.7, 2.0),
        wall_colour=np.array([0.82, 0.8, 0.74]) + rng.uniform(-0.08, 0.08, 3),
        table_colour=np.array([0.55, 0.38, 0.22]) * rng.uniform(0.7, 1.2),
        posters=posters, light=light / np.linalg.norm(light),
    )


def elbow_at(layout: Layout, object_position: np.ndarray) -> np.ndarray:
    """The elbow follows half of the object's excursion from its mean position."""
    return layout.elbow + 0.5 * (np.asarray(object_position) - layout.mean_position)


def hand_parts(state: HandState, object_pose: np.ndarray, elbow: np.ndarray | None) -> Part:
    """Palm (ellipsoid), fingers and thumb (capsules) and forearm (capsule to the elbow; none where ``elbow`` is None),
    in the frame ``object_pose`` maps the object frame to (the camera frame)."""
    T = object_pose @ state.hand_in_object
    R, t = T[:3, :3], T[:3, 3]
    chains = state.chains @ R.T + t  # (5, 4, 3)
    starts = chains[:, :-1].reshape(-1, 3)
    ends = chains[:, 1:].reshape(-1, 3)
    radii = np.repeat(np.array([FINGER_RADIUS] * 4 + [THUMB_RADIUS]), 3)
    radii = radii * np.tile([1.0, 0.93, 0.86], 5)  # fingers taper
    wrist = R @ WRIST + t
    # the forearm ends a little short of the elbow joint (the upper arm, in the sleeve, takes over)
    if elbow is None:
        starts, ends, radii = np.vstack([starts, chains[4, 0]]), np.vstack([ends, wrist]), np.append(radii, THUMB_RADIUS * 1.3)
    else:
        starts = np.vstack([starts, wrist, chains[4, 0]])
        ends = np.vstack([ends, elbow, wrist])
        radii = np.concatenate([radii, [FOREARM_RADIUS, THUMB_RADIUS * 1.3]])
    fingers = capsules(starts, ends, radii, HAND)
    palm = ellipsoids(t[None], (R * PALM[None, :])[None], HAND)
    vertices, faces, normals, _ = concatenate([fingers, palm])
    return Part(vertices, faces, normals, HAND)


def grasp_hand(grasp: Grasp) -> Part:
    """The hand holding ``grasp``: palm, fingers and thumb (no forearm), object frame."""
    return hand_parts(HandState(grasp.hand_in_object, grasp.wrapped, True, 0), np.eye(4), None)


def person_parts(layout: Layout) -> list[Part]:
    """The still part of the person: torso and head (ellipsoids) and neck (capsule), camera frame."""
    torso = ellipsoids(np.stack([layout.torso_centre, layout.head_centre]),
                       np.stack([np.diag(layout.torso_axes), np.diag([layout.head_radius * 0.85, layout.head_radius * 1.1, layout.head_radius])]),
                       PERSON, n_lat=12, n_lon=20)
    neck = capsules(layout.head_centre[None], (layout.torso_centre - np.array([0, layout.torso_axes[1] * 0.8, 0]))[None], np.array([0.05]), PERSON)
    return [torso, neck]


def upper_arm_part(layout: Layout, elbow: np.ndarray) -> Part:
    """The upper arm in its sleeve (a capsule from the shoulder to the elbow), camera frame."""
    return capsules(layout.shoulder[None], np.asarray(elbow)[None], np.array([0.045]), PERSON)


def background_parts(layout: Layout) -> list[Part]:
    """The wall (a large quad facing the camera) and the table top (a horizontal quad)."""
    n = layout.wall_normal
    along = np.cross(n, [0.0, 1.0, 0.0])  # horizontal, in the wall
    wall = quad(layout.wall_centre, along * 6.0, np.array([0.0, 6.0, 0.0]), WALL)
    if np.dot(wall.normals[0], n) < 0:
        wall = quad(layout.wall_centre, -along * 6.0, np.array([0.0, 6.0, 0.0]), WALL)
    far = layout.wall_centre[2]
    near = layout.table_near
    centre = np.array([0.0, layout.table_height, (near + far) / 2])
    table = quad(centre, np.array([0.0, 0.0, (far - near) / 2]), np.array([1.5, 0.0, 0.0]), TABLE)
    if table.normals[0, 1] > 0:  # the top faces up (camera -y)
        table = quad(centre, np.array([1.5, 0.0, 0.0]), np.array([0.0, 0.0, (far - near) / 2]), TABLE)
    return [wall, table]
