"""Reader of REDWOOD75-format ground truth: ``DIR/annotations.json`` plus meshes (``DIR/<mesh>`` or
``DIR/meshes/<mesh>``), as the real REDWOOD75 files and ``reconstruct-sequence`` write them.

The file uses REDWOOD75's raw object axes (raw x = ShapeNet z, raw y = -ShapeNet y, raw z =
ShapeNet x); samples come out in ShapeNet axes, remapped exactly as cpas_toolbox's
AnnotatedRedwoodDataset does with ``remap_y_axis: -y, remap_x_axis: z``: orientation
q_raw * q(shapenet -> raw), extents permuted, mesh vertices rotated. ``scale`` is half the extents.

Instance masks come from ``DIR/masks/<sequence>/<frame id>.png`` where ``reconstruct-sequence``
wrote them, else from the posed true mesh (its box where there is no mesh), ray-cast.

Frames (optional) are looked up under a root as ``ROOT/<sequence>/rgb|depth/<file>`` or
cpas_toolbox's ``ROOT/<category>/rgbd/<sequence>/rgb|depth/<file>``; a ``camera.yaml`` in the
sequence folder overrides Redwood's default camera.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from evaluate.geometry import RAW_FROM_SHAPENET, SHAPENET_FROM_RAW, quat_to_matrix, matrix_to_quat, raw_to_shapenet_extents
from sequences.annotation import default_symmetry
from sequences.camera import Camera
from sequences.documents import load_document
from sequences.errors import InputError
from sequences.names import check_name

from .base import Dataset, load_mesh_file
from .frames import read_instance_ids
from .sample import Sample

ANNOTATIONS = "annotations.json"
#: Instance masks that ``reconstruct-sequence`` writes next to the annotations: ``masks/<sequence>/<frame id>.png``.
MASKS = "masks"
_REDWOOD_NAME = re.compile(r"^(\d+)-(\d+)$")
#: Quaternions further than this from unit norm are rejected rather than silently normalised.
QUATERNION_NORM_TOLERANCE = 1e-3


def frame_id(file_name: str) -> str:
    """Frame id of a colour file: the Redwood frame number (``0000210`` of ``0000210-000007004844.jpg``), else the stem."""
    stem = Path(file_name).stem
    match = _REDWOOD_NAME.match(stem)
    return match.group(1) if match else stem


def raw_to_shapenet_orientation(orientation_raw) -> np.ndarray:
    """Quaternion (x, y, z, w) of the raw-axes object to camera -> that of the ShapeNet-axes object.

    R_shapenet = R_raw @ RAW_FROM_SHAPENET (ShapeNet coordinates -> raw coordinates -> camera).
    """
    return matrix_to_quat(quat_to_matrix(orientation_raw) @ RAW_FROM_SHAPENET)


class Redwood75Dataset(Dataset):
    """REDWOOD75-format ground truth in ShapeNet axes."""

    name = "redwood75"

    def __init__(self, root: str | Path, frames: str | Path | None = None) -> None:
        root = Path(root)
        path = root / ANNOTATIONS
        if not path.is_file():
            raise InputError(path, "not found (a REDWOOD75-format dataset folder holds annotations.json and the meshes)")
        data = load_document(path, "annotations file", as_yaml=False)
        if not isinstance(data, dict) or not data:
            raise InputError(path, "expected a non-empty mapping {sequence: {category, mesh, scale, pose_anns}}")
        frames_root = None if frames is None else Path(frames)
        if frames_root is not None and not frames_root.is_dir():
            raise InputError(frames_root, "frames root is not a folder")
        samples: list[Sample] = []
        self.missing_meshes: list[str] = []  # sequences whose mesh file is absent (shape metrics skipped)
        for sequence, entry in data.items():
            # names, never paths: they build the paths of frames, masks and meshes read below
            samples.extend(self._parse_sequence(path, check_name(str(sequence), "sequence name", path), entry, root, frames_root))
        super().__init__(samples, root)
        self.name = root.name or self.name

    def _parse_sequence(self, path: Path, sequence: str, entry, root: Path, frames_root: Path | None) -> list[Sample]:
        where = f"sequence {sequence}"
        if not isinstance(entry, dict):
            raise InputError(path, f"{where}: expected a mapping, got {type(entry).__name__}")
        for key in ("category", "scale", "pose_anns"):
            if key not in entry:
                raise InputError(path, f"{where}: missing key {key!r}")
        category = entry["category"]
        if not isinstance(category, str) or not category:
            raise InputError(path, f"{where}: category must be a non-empty string")
        symmetry = entry.get("symmetry", default_symmetry(category))
        if symmetry not in ("none", "y"):
            raise InputError(path, f"{where}: symmetry must be 'none' or 'y', got {symmetry!r}")
        half = _vector(path, f"{where}: scale", entry["scale"], 3)
        if (half <= 0).any():
            raise InputError(path, f"{where}: scale (half extents) must be positive, got {half.tolist()}")
        extents = raw_to_shapenet_extents(2.0 * half)
        mesh_path = self._mesh_path(path, where, entry.get("mesh"), root, sequence)
        seq_dir = _sequence_folder(frames_root, category, sequence)
        camera = Camera.from_yaml(seq_dir / "camera.yaml") if seq_dir is not None and (seq_dir / "camera.yaml").is_file() else Camera()
        anns = entry["pose_anns"]
        if not isinstance(anns, list):
            raise InputError(path, f"{where}: pose_anns must be a list")
        samples = []
        for i, ann in enumerate(anns):
            at = f"{where}: pose_anns[{i}]"
            if not isinstance(ann, dict):
                raise InputError(path, f"{at}: expected a mapping")
            for key in ("position", "orientation", "rgb_file", "depth_file"):
                if key not in ann:
                    raise InputError(path, f"{at}: missing key {key!r}")
            position = _vector(path, f"{at}: position", ann["position"], 3)
            q = _vector(path, f"{at}: orientation", ann["orientation"], 4)
            norm = float(np.linalg.norm(q))
            if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
                raise InputError(path, f"{at}: orientation is not a unit quaternion (norm {norm:.6g})")
            rgb, depth = ann["rgb_file"], ann["depth_file"]
            if not isinstance(rgb, str) or not isinstance(depth, str):
                raise InputError(path, f"{at}: rgb_file and depth_file must be strings")
            check_name(rgb, f"{at}: rgb_file", path)
            check_name(depth, f"{at}: depth_file", path)
            samples.append(
                Sample(
                    dataset=self.name,
                    sequence=sequence,
                    frame=frame_id(rgb),
                    category=category,
                    symmetry=symmetry,
                    position=position,
                    orientation=raw_to_shapenet_orientation(q / norm),
                    extents=extents,
                    camera=camera,
                    color_path=None if seq_dir is None else seq_dir / "rgb" / rgb,
                    depth_path=None if seq_dir is None else seq_dir / "depth" / depth,
                    mesh_path=mesh_path,
                    mask_path=_existing(root / MASKS / sequence / f"{frame_id(rgb)}.png"),
                )
            )
        keys = [s.frame for s in samples]
        if len(set(keys)) != len(keys):
            raise InputError(path, f"{where}: two pose annotations share a colour frame")
        return samples

    def _mesh_path(self, path: Path, where: str, mesh, root: Path, sequence: str) -> Path | None:
        if mesh is None:
            self.missing_meshes.append(sequence)
            return None
        if not isinstance(mesh, str) or not mesh:
            raise InputError(path, f"{where}: mesh must be a file name")
        check_name(mesh, f"{where}: mesh", path)
        for candidate in (root / mesh, root / "meshes" / mesh):
            if candidate.is_file():
                return candidate
        self.missing_meshes.append(sequence)
        return None

    def mask(self, sample: Sample, depth: np.ndarray | None = None) -> np.ndarray:
        """The instance mask ``reconstruct-sequence`` wrote (``masks/<sequence>/<frame id>.png``, non-zero =
        object) where there is one, else the posed true mesh ray-cast with cpas_toolbox's occlusion rule."""
        if sample.mask_path is not None:
            return read_instance_ids(sample.mask_path, sample.camera) > 0
        return super().mask(sample, depth)

    def _load_mesh(self, path: Path):
        mesh = load_mesh_file(path)
        # raw -> ShapeNet axes: a proper rotation, so faces keep their winding
        mesh.vertices = np.asarray(mesh.vertices) @ SHAPENET_FROM_RAW.T
        return mesh


def _existing(path: Path) -> Path | None:
    return path if path.is_file() else None


def _sequence_folder(frames_root: Path | None, category: str, sequence: str) -> Path | None:
    """The sequence's frame folder under the root, in our layout or cpas_toolbox's; None when neither exists."""
    if frames_root is None:
        return None
    for candidate in (frames_root / sequence, frames_root / category / "rgbd" / sequence):
        if (candidate / "rgb").is_dir():
            return candidate
    return None


def _vector(path: Path, where: str, value, n: int) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise InputError(path, f"{where}: expected a list of {n} numbers, got {value!r}"[:200])
    if not all(math.isfinite(v) for v in value):
        raise InputError(path, f"{where}: non-finite value in {value!r}")
    return np.asarray(value, dtype=np.float64)
