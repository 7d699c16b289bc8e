"""The capture plan of a synthetic sequence: the object's path and the hand's grasps, for each coverage.

- ``every_side`` (:func:`.motion.object_trajectory`): the object is turned through all orientations,
  its opening and its bottom to the camera, regrasped once or more.
- ``key_orientations``: the object passes through a few key orientations only, dwelling at each with a
  hand's tremor and turning between them, as people show an object: the real orientations of a
  REDWOOD75 sequence, or a few drawn the same way. The bottom or the opening may never be seen.
- ``table``: the object rests on a table (no hand), is picked up (lifted before it turns), shown, set down in
  another orientation (its turn coming to rest as it lands), left, picked up again and shown. Held over the
  table, it never sinks into it: the held path is raised where needed before the lift blends into it.

Frames: camera OpenCV (x right, y down, z forward), metres; rotations map object (ShapeNet axes) to camera.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, RotationSpline

from ..axes import raw_to_shapenet_rotation
from ..errors import InputError
from .motion import FRAMES_PER_KEY, Trajectory, _key_rotations, _unit, drift_positions, grasp_schedule, held_frames, object_trajectory

#: The pace of turning between key orientations, degrees per frame at turn speed 1 (as the every-side path).
DEGREES_PER_FRAME = 4.5
#: A hand's tremor while an orientation is shown: standard deviation of the rotation (degrees) at each dwell knot.
TREMOR_DEG = 2.5
#: Drawn key orientations: how many, and the largest tilt (degrees) of the object's y axis from up.
DRAWN_KEYS = 5
DRAWN_TILT_DEG = 120.0
#: The table coverage's phases as shares of the frames: resting, held, resting again (in another orientation),
#: then held to the end; and the frames over which the object is lifted off or set down.
TABLE_PHASES = (0.18, 0.32, 0.18)
LIFT_FRAMES = 10


@dataclass
class CapturePlan:
    """The object's path, the grasps' frame ranges and the frames where it rests (no hand) over a sequence."""

    trajectory: Trajectory
    schedule: list[tuple[int, int]]  # (first, last) held frames per grasp
    resting: np.ndarray  # (frames,) bool
    table: tuple[float, float] | None = None  # table top's camera y and the camera z of its front edge, if the plan needs it


def redwood75_keys(spec: str) -> np.ndarray:
    """(K, 3, 3) object-to-camera rotations (ShapeNet axes) of a REDWOOD75 sequence's annotations, in their order.

    ``spec`` is ``FILE:ID``: a REDWOOD75 annotations.json (raw object axes) and a sequence id in it.
    """
    path, _, sequence = spec.rpartition(":")
    if not path or not sequence:
        raise InputError(spec, "key orientations must be given as FILE:SEQUENCE (a REDWOOD75 annotations.json and an id in it)")
    try:
        data = json.loads(Path(path).read_text())
        anns = data[sequence]["pose_anns"]
        quats = np.array([a["orientation"] for a in anns], dtype=np.float64)
    except FileNotFoundError as error:
        raise InputError(path, "key orientation file not found") from error
    except KeyError as error:
        raise InputError(path, f"no sequence {sequence!r} with pose_anns in it ({error})") from error
    except (OSError, ValueError, TypeError) as error:
        raise InputError(path, f"not a REDWOOD75 annotations file ({error.__class__.__name__})") from error
    if quats.ndim != 2 or quats.shape[1] != 4 or len(quats) < 2 or not np.all(np.isfinite(quats)):
        raise InputError(path, f"sequence {sequence!r} needs two or more finite x y z w orientations")
    return raw_to_shapenet_rotation(Rotation.from_quat(quats).as_matrix())


def drawn_keys(rng: np.random.Generator) -> np.ndarray:
    """(DRAWN_KEYS, 3, 3) orientations as people show an object: upright first, then its y axis tilted from up by up to
    DRAWN_TILT_DEG toward a random side, spun about y at random."""
    rotations = []
    for k in range(DRAWN_KEYS):
        tilt = np.radians(rng.uniform(0.0, 20.0) if k == 0 else rng.uniform(0.0, DRAWN_TILT_DEG))
        azimuth = rng.uniform(-np.pi, np.pi)
        y = np.array([np.sin(tilt) * np.cos(azimuth), -np.cos(tilt), np.sin(tilt) * np.sin(azimuth)])  # camera y is down
        spin = Rotation.from_rotvec([0.0, rng.uniform(-np.pi, np.pi), 0.0])
        upright = Rotation.from_matrix(np.diag([-1.0, -1.0, 1.0]))  # object y up, its -z (a handle) toward the camera
        turn = Rotation.align_vectors(y[None], [[0.0, -1.0, 0.0]])[0]
        rotations.append((turn * upright * spin).as_matrix())
    return np.stack(rotations)


def key_orientation_trajectory(frames: int, keys: np.ndarray, rng: np.random.Generator, turn_speed: float = 1.0) -> Trajectory:
    """A path through ``keys`` (K, 3, 3) in order: a dwell at each (tremor of TREMOR_DEG) and turns between them at
    DEGREES_PER_FRAME x ``turn_speed`` (faster where the frames would not suffice)."""
    keys = Rotation.from_matrix(keys)
    angles = np.degrees(np.linalg.norm((keys[:-1].inv() * keys[1:]).as_rotvec(), axis=1))
    turns = np.maximum(angles / (DEGREES_PER_FRAME * turn_speed), 3.0)
    budget = 0.7 * (frames - 1)  # at least 30 % of the frames dwell
    turns *= min(1.0, budget / turns.sum())
    dwell = (frames - 1 - turns.sum()) / len(keys)
    times, knots = [], []
    t = 0.0
    for k in range(len(keys)):  # a few keys
        for end in (0.0, dwell):
            times.append(t + end)
            knots.append(Rotation.from_rotvec(rng.normal(0.0, np.radians(TREMOR_DEG) / np.sqrt(3), 3)) * keys[k])
        t += dwell + (turns[k] if k < len(turns) else 0.0)
    times = np.array(times)
    keep = np.concatenate([[True], np.diff(times) > 1e-6])  # a zero dwell leaves one knot per key
    spline = RotationSpline(times[keep], Rotation.concatenate([knots[i] for i in np.flatnonzero(keep)]))
    frame_times = np.clip(np.arange(frames, dtype=float), times[0], times[keep][-1])
    return Trajectory(spline(frame_times).as_matrix(), drift_positions(np.linspace(0.0, 1.0, frames), len(keys), rng))


def _eased_times(a: int, b: int, settles: bool) -> np.ndarray:
    """Spline times (b - a + 1,) for held frames ``a..b`` of a path keyed from ``a - 1`` to ``b + 1``: the turn
    starts from rest over LIFT_FRAMES (a hand lifts before it turns) and, if it ``settles`` on the table, comes to
    rest over as many; constant pace between, a little faster to keep the keys' times."""
    span = b - a + 2
    u = (np.arange(a, b + 1) - (a - 1)) / span
    ramp = min(LIFT_FRAMES / span, 0.45)
    pace = 1.0 / (1.0 - ramp) if settles else 1.0 / (1.0 - ramp / 2)
    eased = np.where(u < ramp, pace * u * u / (2 * ramp), pace * (u - ramp / 2))
    if settles:
        eased = np.where(u > 1 - ramp, 1.0 - pace * (1 - u) ** 2 / (2 * ramp), eased)
    return (a - 1) + span * eased


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def resting_pose(vertices: np.ndarray, rotation: np.ndarray, x: float, z: float, table_y: float) -> np.ndarray:
    """Box-centre position (3,) of an object (vertices (V, 3), object frame) turned by ``rotation`` so that its lowest
    point lies on the table top at camera y ``table_y`` (camera y points down)."""
    return np.array([x, table_y - float((vertices @ rotation.T)[:, 1].max()), z])


def table_trajectory(frames: int, vertices: np.ndarray, rng: np.random.Generator, turn_speed: float = 1.0) -> CapturePlan:
    """Rest, pick up, show, put down (upside down or upright, turned), rest, pick up, show (see the module notes)."""
    rest_a = int(round(TABLE_PHASES[0] * frames))
    held_a = int(round(TABLE_PHASES[1] * frames))
    rest_b = int(round(TABLE_PHASES[2] * frames))
    first, second = (rest_a, rest_a + held_a - 1), (rest_a + held_a + rest_b, frames - 1)
    table_y, x, z = rng.uniform(0.10, 0.16), rng.uniform(-0.06, 0.06), rng.uniform(0.68, 0.78)
    table_near = z - rng.uniform(0.12, 0.18)
    upright = Rotation.from_matrix(np.diag([-1.0, -1.0, 1.0]))
    yaw = lambda: Rotation.from_rotvec([0.0, rng.uniform(-np.pi, np.pi), 0.0])  # noqa: E731
    flipped = Rotation.from_rotvec([0.0, 0.0, np.pi]) if rng.random() < 0.5 else Rotation.identity()
    rests = [upright * yaw(), flipped * upright * yaw()]
    spots = [resting_pose(vertices, r.as_matrix(), x, z, table_y) for r in rests]
    spots[1][0] = x + rng.uniform(-0.05, 0.05)
    R = np.empty((frames, 3, 3))
    P = np.empty((frames, 3))
    R[: first[0]], P[: first[0]] = rests[0].as_matrix(), spots[0]
    R[second[0] - rest_b : second[0]] = rests[1].as_matrix()
    P[second[0] - rest_b : second[0]] = spots[1]
    sides = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, -1.0], [0, 0, 1.0]])
    for (a, b), start, spot, end in ((first, rests[0], spots[0], rests[1]), (second, rests[1], spots[1], None)):
        n = b - a + 1
        keys = max(2, int(round(n * turn_speed / FRAMES_PER_KEY)))
        targets = [_unit(sides[rng.integers(4)] + rng.normal(0, 0.2, 3)) if k % 2 == 0 else _unit(np.array([0.0, 1.0 if k % 4 == 1 else -1.0, 0.0]) + rng.normal(0, 0.2, 3))
                   for k in range(keys)]
        turns = _key_rotations(start, targets, rng.uniform(-1.4, 1.4, keys))
        times = np.linspace(a - 1, b + 1, keys + 1)
        if end is not None:  # the last key sets it down in its next resting orientation
            turns[-1] = end
        spline = RotationSpline(times, Rotation.concatenate(turns))
        R[a : b + 1] = spline(_eased_times(a, b, settles=end is not None)).as_matrix()
        # The held path clears the table at every orientation; the lift and the landing blend from the resting spot
        # into it, so the object rises and comes down without a jump.
        drift = drift_positions(np.linspace(0.0, 1.0, n), keys, rng)
        held = _above_table(drift, R[a : b + 1], vertices, table_y, table_near, resting=np.zeros(n, bool))
        lift = _smoothstep((np.arange(n) + 1) / LIFT_FRAMES)[:, None]
        P[a : b + 1] = (1 - lift) * spot + lift * held
        if end is not None:
            land = _smoothstep((b + 1 - np.arange(a, b + 1)) / LIFT_FRAMES)[:, None]
            P[a : b + 1] = land * P[a : b + 1] + (1 - land) * spots[1]
    # What the blend of a turning object still sinks (a few millimetres near the spot) is raised too.
    resting = _resting(frames, [first, second])
    P = _above_table(P, R, vertices, table_y, table_near, resting=resting)
    return CapturePlan(Trajectory(R, P), [first, second], resting, (table_y, table_near))


def _resting(frames: int, schedule: list[tuple[int, int]]) -> np.ndarray:
    return ~held_frames(frames, schedule)


def _above_table(P: np.ndarray, R: np.ndarray, vertices: np.ndarray, table_y: float, table_near: float, resting: np.ndarray) -> np.ndarray:
    """Positions (N, 3) raised (camera -y) where a held object would sink into the table: its lowest point kept at or
    above the top wherever it is over the table; the raise is spread over neighbouring frames so the path stays
    smooth (a running maximum, then a moving average no wider: never below the raise needed)."""
    turned = np.einsum("nij,vj->nvi", R, vertices)  # (N, V, 3): a hull's few hundred vertices
    lowest = turned[:, :, 1].max(axis=1) + P[:, 1]
    far = turned[:, :, 2].max(axis=1) + P[:, 2]
    over = (far > table_near) & ~resting
    need = np.where(over, np.clip(lowest - table_y, 0.0, None), 0.0)
    padded = np.pad(need, 5, mode="edge")
    running = np.lib.stride_tricks.sliding_window_view(padded, 11).max(axis=1)
    smooth = np.convolve(np.pad(running, 2, mode="edge"), np.ones(5) / 5, mode="valid")
    out = P.copy()
    out[:, 1] -= np.where(resting, 0.0, smooth)
    return out


def capture_plan(coverage: str, frames: int, vertices: np.ndarray, rng: np.random.Generator, keys: str | None = None,
                 turn_speed: float = 1.0) -> CapturePlan:
    """The object's path and grasp schedule for a ``coverage`` (see the module notes); ``vertices`` (V, 3) of the object."""
    if coverage == "every_side":
        schedule = grasp_schedule(frames)
        trajectory = object_trajectory(frames, rng, held_frames(frames, schedule), turn_speed)
        return CapturePlan(trajectory, schedule, np.zeros(frames, bool))
    if coverage == "key_orientations":
        rotations = redwood75_keys(keys) if keys is not None else drawn_keys(rng)
        return CapturePlan(key_orientation_trajectory(frames, rotations, rng, turn_speed), grasp_schedule(frames), np.zeros(frames, bool))
    if coverage == "table":
        return table_trajectory(frames, vertices, rng, turn_speed)
    raise ValueError(f"unknown coverage {coverage!r}")
