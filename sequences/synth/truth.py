"""The synthetic sequence's ground truth in ``SEQ/truth/``: writing it, reading it back, and annotations made from it.

``truth/mesh.obj``: the object in its own frame (ShapeNet axes, metres, centred on its box).
``truth/truth.json``: ``{category, symmetry, extents, poses: {frame id: {position, orientation}}}``
(poses map object to camera, quaternions x y z w, as in the annotation document) plus the
generator's notes (seed, camera, grasps, whether the hand holds the object in each frame).
``truth/masks/<frame id>.png``: uint8, 255 where the object is the visible surface, else 0.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from PIL import Image
from scipy.spatial.transform import Rotation

from ..annotation import Annotation, FramePose
from ..errors import InputError
from ..truth import Truth

TRUTH_DIR = "truth"


def _mask_reader(root: Path) -> Callable[[str], np.ndarray]:
    def mask(frame_id: str) -> np.ndarray:
        path = root / TRUTH_DIR / "masks" / f"{frame_id}.png"
        try:
            return np.asarray(Image.open(path)) > 127
        except FileNotFoundError as error:
            raise InputError(path, f"no truth mask for frame {frame_id}") from error

    return mask


def write_mask(root: Path, frame_id: str, mask: np.ndarray) -> None:
    """Write ``truth/masks/<frame id>.png`` (uint8 0/255)."""
    Image.fromarray((mask * 255).astype(np.uint8)).save(root / TRUTH_DIR / "masks" / f"{frame_id}.png", compress_level=1)


def pose_entry(T: np.ndarray) -> dict:
    """A 4x4 pose as the document's ``{position, orientation}`` (quaternion x y z w, w >= 0)."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    q = q if q[3] >= 0 else -q
    return {"position": [float(x) for x in T[:3, 3]], "orientation": [float(x) for x in q]}


def write_truth(root: Path, category: str, symmetry: str, mesh: trimesh.Trimesh, poses: dict[str, np.ndarray], notes: dict) -> None:
    """Write ``truth/mesh.obj`` and ``truth/truth.json`` (masks are written frame by frame)."""
    folder = root / TRUTH_DIR
    folder.mkdir(parents=True, exist_ok=True)
    mesh.export(folder / "mesh.obj", file_type="obj", include_normals=False, digits=9)
    document = {
        "category": category,
        "symmetry": symmetry,
        "extents": [float(x) for x in mesh.extents],
        "poses": {frame_id: pose_entry(T) for frame_id, T in poses.items()},
    }
    document.update({k: v for k, v in notes.items() if k not in document})
    (folder / "truth.json").write_text(json.dumps(document, indent=1))


def load_truth(sequence_root: str | Path) -> Truth:
    """Read ``SEQ/truth/`` (see the module notes); raises InputError for a missing or malformed truth."""
    root = Path(sequence_root)
    path = root / TRUTH_DIR / "truth.json"
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as error:
        raise InputError(path, "no truth file (only synthetic sequences have truth/)") from error
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(path, f"unreadable truth file ({error.__class__.__name__})") from error
    try:
        poses = {}
        for frame_id, entry in data["poses"].items():
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(entry["orientation"]).as_matrix()
            T[:3, 3] = entry["position"]
            poses[str(frame_id)] = T
        category, symmetry = str(data["category"]), str(data["symmetry"])
        extents = np.asarray(data["extents"], dtype=np.float64).reshape(3)
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(path, f"malformed truth file ({error.__class__.__name__}: {error})") from error
    mesh_path = root / TRUTH_DIR / "mesh.obj"
    try:
        mesh = trimesh.load(mesh_path, force="mesh", process=False)
    except Exception as error:
        raise InputError(mesh_path, f"unreadable truth mesh ({error.__class__.__name__})") from error
    notes = {k: v for k, v in data.items() if k not in ("category", "symmetry", "extents", "poses")}
    return Truth(root, category, symmetry, extents, poses, mesh, notes, masks=_mask_reader(root))


def truth_annotation(truth: Truth, manual_ids, rotation_deg: float = 0.0, translation_m: float = 0.0,
                     extents_rel: float = 0.0, seed: int = 0) -> Annotation:
    """An annotation document whose ``manual`` frames are the true poses perturbed by up to the given amounts.

    Each manual frame's rotation is composed with a rotation about a uniformly random axis by an
    angle uniform in [0, rotation_deg] degrees; its position moves in a uniformly random direction
    by a distance uniform in [0, translation_m] metres; the extents are scaled per axis by a
    factor uniform in [1 - extents_rel, 1 + extents_rel]. Frames not listed have no pose.
    """
    rng = np.random.default_rng(seed)
    manual_ids = [str(i) for i in manual_ids]
    missing = [i for i in manual_ids if i not in truth.poses]
    if missing:
        raise InputError(truth.root / TRUTH_DIR / "truth.json", f"frames {missing[:5]} have no true pose")
    frames = {}
    for frame_id in manual_ids:  # a few frames: one small 4x4 each
        T = truth.poses[frame_id].copy()
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = np.deg2rad(rotation_deg) * rng.uniform()
        T[:3, :3] = Rotation.from_rotvec(axis * angle).as_matrix() @ T[:3, :3]
        direction = rng.normal(size=3)
        T[:3, 3] += direction / np.linalg.norm(direction) * translation_m * rng.uniform()
        frames[frame_id] = FramePose.from_matrix(T, "manual")
    extents = truth.extents * (1.0 + rng.uniform(-extents_rel, extents_rel, 3))
    return Annotation(sequence=truth.root.resolve().name, category=truth.category if truth.category else "other",
                      symmetry=truth.symmetry, extents=extents, frames=frames)
