"""One frame against one model: crop by the predicted box, register, weigh a symmetric object's spin by what the
registration measured of it, measure."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from evaluate.geometry import invert, rotation_about_y, untransform

from . import icp
from .config import TrackingConfig
from .frames import FrameStore
from .model import ObjectModel
from .quality import in_box_share
from .registration import ModelTarget, register
from .sampling import every_kth
from annotate.symmetry_axis import closest_about_y


#: The model parts kept for reuse (bytes): a mug frame's part is about 100 kB, a laptop's about 450 kB.
MODEL_PART_BYTES = 64 << 20


#: a symmetric object's spin about its y, as registered, is weighed against the predicted spin with this sigma (deg,
#: the change of spin between frames a hand makes): a body of revolution measures no spin and keeps the prediction;
#: a flattened bottle or a square bowl measures it and keeps its own
SPIN_PRIOR_DEG = 1.5
#: the spin's information is measured by turning the points this far (deg) either way and pairing them afresh
SPIN_PROBE_DEG = 2.0
#: a registration's points count as at most this many independent ones: neighbouring points' errors correlate
INDEPENDENT_POINTS = 100


def spin_information(points: np.ndarray, target: ModelTarget, distance: float, sigma: float) -> float:
    """Information (1/rad^2) on the spin about the object's y of object-frame ``points`` (N, 3) registered to ``target``:
    the curvature of their summed squared point-to-plane residuals (each capped at ``distance``, m; ``sigma``: the
    point noise, m) as they turn SPIN_PROBE_DEG either way, paired afresh each time. Pairing afresh makes a surface
    of revolution measure no spin however noisy its model's normals: its turned points still lie on it (the
    Jacobian through the normals would count their noise times the radius as information)."""
    if len(points) == 0 or len(target) == 0:
        return 0.0
    normals = np.asarray(target.cloud.normals)
    delta = np.radians(SPIN_PROBE_DEG)
    costs = []
    for angle in (-delta, 0.0, delta):
        turned = points @ rotation_about_y(angle).T
        gap, index = target.nearest(turned, 2 * distance)
        near = np.isfinite(gap)
        residual = np.full(len(points), distance)
        residual[near] = np.minimum(np.abs(np.einsum("ij,ij->i", turned[near] - target.points[index[near]], normals[index[near]])), distance)
        costs.append(float(np.sum(residual**2)))
    scale = min(1.0, INDEPENDENT_POINTS / len(points))
    return max(costs[0] + costs[2] - 2 * costs[1], 0.0) / (2 * delta**2 * sigma**2) * scale


def measured_spin(pose: np.ndarray, predicted: np.ndarray, information: float) -> np.ndarray:
    """``pose`` (4x4) with its spin about its y moved from ``predicted``'s spin towards its own as far as the
    registration measured it: the spin's ``information`` (1/rad^2, :func:`spin_information`) against the prior of
    SPIN_PRIOR_DEG (a Gaussian's posterior mean). The y axis and the centre stay the registration's."""
    kept = closest_about_y(pose[:3, :3], predicted[:3, :3])
    turn = kept.T @ pose[:3, :3]  # a rotation about y
    angle = np.arctan2(turn[0, 2], turn[2, 2])
    weight = information / (information + np.radians(SPIN_PRIOR_DEG) ** -2)
    out = pose.copy()
    out[:3, :3] = kept @ rotation_about_y(weight * angle)
    return out


def _nbytes(part: tuple) -> int:
    return sum(a.nbytes for a in part if isinstance(a, np.ndarray))


@dataclass
class FrameResult:
    """A frame's pose (4x4 object to camera), whether registration succeeded, and its quality figures."""

    pose: np.ndarray
    ok: bool
    figures: dict = field(default_factory=dict)


class Tracker:
    """Registers frames of one sequence to object models, with one configuration and one box size."""

    def __init__(self, store: FrameStore, extents: np.ndarray, symmetric: bool, config: TrackingConfig) -> None:
        self.store = store
        self.config = config
        self.symmetric = symmetric
        self.extents = np.asarray(extents, dtype=np.float64)
        # hand-placed extents are off by several percent: crop and judge with a slightly larger box
        self.box = self.extents * (1.0 + config.extents_slack)
        # before any worker forks, or each would load them again; every backend needs them (the models' searches)
        icp.load_kernels()

    def new_model(self) -> ObjectModel:
        return ObjectModel(self.config.voxel_size, self.box, margin=self.config.voxel_size)

    def crop(self, frame_id: str, pose: np.ndarray, margin: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        margin = self.config.crop_margin if margin is None else margin
        return self.store.crop(frame_id, pose, self.box, margin, self.config.voxel_size)

    def add_to_model(self, model: ObjectModel, frame_id: str, pose: np.ndarray, weight: int = 1) -> None:
        """Add the frame cropped by the box at ``pose`` (4x4) to ``model``."""
        model.add_frame(*self.crop(frame_id, pose, margin=0.0), pose, weight)

    def add_frames_to_model(self, model: ObjectModel, frame_ids: list[str], poses: list[np.ndarray], weight: int = 1) -> None:
        """Add the frames, in order, each cropped by the box at its pose, to ``model``: the crops on the workers
        (FrameStore.crops) and one merge (ObjectModel.add_parts).

        A frame's part (its voxels in the model's grid) is kept in ``store.model_parts`` (``MODEL_PART_BYTES`` of them)
        and reused where the frame comes again at the same pose, to the last bit: the checks after the refinement build
        many models of the same few poses."""
        store, grid = self.store, model.grid_key()
        keys = [(f, np.asarray(pose, dtype=np.float64).tobytes(), self.box.tobytes(), self.config.voxel_size, weight, grid) for f, pose in zip(frame_ids, poses)]
        parts = {key: store.model_parts[key] for key in keys if key in store.model_parts}
        todo = [i for i, key in enumerate(keys) if key not in parts]
        crops = store.crops([(frame_ids[i], poses[i]) for i in todo], self.box, 0.0, self.config.voxel_size, self.config.worker_count())
        for i, (points, colors) in zip(todo, crops):
            parts[keys[i]] = model.frame_part(points, colors, poses[i], weight)
        for key in keys:  # kept in the order of use: the least recently used dropped first
            store.model_parts[key] = parts[key]
            store.model_parts.move_to_end(key)
        held, budget = sum(_nbytes(p) for p in store.model_parts.values()), MODEL_PART_BYTES if store.cache else 0
        while store.model_parts and held > budget:
            held -= _nbytes(store.model_parts.popitem(last=False)[1])
        model.add_parts([parts[key] for key in keys])

    def register(self, frame_id: str, init_pose: np.ndarray, model: ObjectModel, min_hits: int = 1, refresh_every: int = 1) -> FrameResult:
        """Register a frame to ``model`` starting from ``init_pose`` (4x4); never raises on bad data."""
        config = self.config
        points, colors = self.crop(frame_id, init_pose)
        figures: dict = {"points": int(len(points))}
        if frame_id in self.store.errors:
            figures["error"] = self.store.errors[frame_id]
            return FrameResult(init_pose.copy(), False, figures)
        if len(points) < config.min_points:
            figures["error"] = f"only {len(points)} points in the box"
            return FrameResult(init_pose.copy(), False, figures)
        target = model.target(min_hits, refresh_every=refresh_every)
        # a large flat object (a laptop) crops to thousands of voxels: every k-th bounds the ICP's time
        points, colors = every_kth(points, config.max_points), (every_kth(colors, config.max_points) if colors is not None else None)
        result = register(points, target, invert(init_pose), config.backend, config.registration, colors)
        if not result.ok:
            figures["error"] = result.reason
            return FrameResult(init_pose.copy(), False, figures)
        pose = invert(result.transform)
        if self.symmetric:
            information = spin_information(untransform(pose, points), target, config.registration.fine_distance, config.information_sigma)
            pose = measured_spin(pose, init_pose, information)
        figures["fitness"] = result.fitness
        figures["inlier_rmse"] = result.inlier_rmse
        figures["in_box"] = in_box_share(points, pose, self.box)
        return FrameResult(pose, True, figures)
