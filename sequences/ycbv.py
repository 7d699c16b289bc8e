"""YCB-Video's layout: real Asus Xtion (PrimeSense) frames of static YCB objects with their true poses.

A video folder holds ``NNNNNN-color.jpg|png`` (640x480 RGB), ``NNNNNN-depth.png`` (uint16, metres =
value / depth_factor; registered to colour), ``NNNNNN-label.png`` (per-pixel class: 0 background, 1-21 in
:data:`YCB_CLASSES` order) and ``poses.json`` (``{"frames": {"NNNNNN": {"K": 3x3, "depth_factor": f,
"objects": {name: 3x4 [R | t]}}}}``, model frame to camera, metres, OpenCV axes; the dataset's
meta.mat in JSON). Models lie in ``<video>/../models/<name>/`` (``model.obj`` where there is one,
``points.xyz`` always), metres, YCB axes (z up), their origin not at the box centre.

:func:`open_ycbv_video` opens a video as a :class:`Sequence` (frame ids are the six-digit numbers; colour
and depth share them). :func:`load_ycbv_truth` gives one object's truth in the toolkit's conventions:
ShapeNet axes (:data:`sequences.axes.SHAPENET_FROM_YCB`), centred on the box of its model points.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import trimesh

from .annotation import default_symmetry
from .axes import SHAPENET_FROM_YCB
from .camera import Camera
from .documents import load_document
from .errors import InputError
from .images import read_labels
from .reader import FrameFiles, Sequence
from .truth import Truth

#: YCB-Video's 21 classes, in label order (label value = index + 1).
YCB_CLASSES = (
    "002_master_chef_can", "003_cracker_box", "004_sugar_box", "005_tomato_soup_can", "006_mustard_bottle",
    "007_tuna_fish_can", "008_pudding_box", "009_gelatin_box", "010_potted_meat_can", "011_banana",
    "019_pitcher_base", "021_bleach_cleanser", "024_bowl", "025_mug", "035_power_drill", "036_wood_block",
    "037_scissors", "040_large_marker", "051_large_clamp", "052_extra_large_clamp", "061_foam_brick",
)
#: The category an annotator would give each YCB object (REDWOOD75's six, else "other"): dataset metadata only.
YCB_CATEGORIES = {
    "002_master_chef_can": "can", "005_tomato_soup_can": "can", "007_tuna_fish_can": "can", "010_potted_meat_can": "can",
    "006_mustard_bottle": "bottle", "021_bleach_cleanser": "bottle", "024_bowl": "bowl", "025_mug": "mug",
}
_FRAME = re.compile(r"^(\d+)-color$")


def _poses_document(root: Path) -> dict:
    path = root / "poses.json"
    data = load_document(path, "poses file", as_yaml=False)
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, dict) or not frames:
        raise InputError(path, "expected {\"frames\": {frame id: {K, depth_factor, objects}}}")
    return frames


def _camera(path: Path, entry: dict) -> Camera:
    """A frame's camera: ``K`` and ``depth_factor`` (units per metre); YCB-Video's images are 640x480."""
    if not isinstance(entry, dict) or "K" not in entry or "depth_factor" not in entry:
        raise InputError(path, "a frame's K or depth_factor is missing")
    try:
        factor = float(entry["depth_factor"])
    except (TypeError, ValueError) as error:
        raise InputError(path, f"a frame's depth_factor is malformed ({error.__class__.__name__})") from error
    if not factor > 0:
        raise InputError(path, f"depth_factor must be positive, got {factor}")
    return Camera.from_matrix(path, entry["K"], 1.0 / factor)


def open_ycbv_video(root: str | Path) -> Sequence:
    """A YCB-Video video folder as a sequence; its camera from ``poses.json`` (the first frame's K and depth_factor)."""
    root = Path(root)
    frames = []
    for colour in sorted(root.glob("*-color.*")):  # a few thousand file names at most
        match = _FRAME.match(colour.stem)
        if not match:
            continue
        depth = root / f"{match.group(1)}-depth.png"
        if depth.is_file():
            frames.append(FrameFiles(match.group(1), colour, depth))
    if not frames:
        raise InputError(root, "no NNNNNN-color.* frame has its NNNNNN-depth.png (YCB-Video layout)")
    document = _poses_document(root)
    first = document.get(frames[0].id)
    if not isinstance(first, dict):
        raise InputError(root / "poses.json", f"no entry for frame {frames[0].id}")
    return Sequence.from_frames(root, frames, _camera(root / "poses.json", first), "ycbv")


def _object_frame(points_ycb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 4x4 transform from the toolkit's object frame (ShapeNet axes, box-centred) to the YCB model frame, and the
    model's points in the toolkit's frame."""
    centre = (points_ycb.min(axis=0) + points_ycb.max(axis=0)) / 2
    A = np.eye(4)
    A[:3, :3] = SHAPENET_FROM_YCB.T  # p_model = SHAPENET_FROM_YCB^T p_obj + centre
    A[:3, 3] = centre
    return A, (points_ycb - centre) @ SHAPENET_FROM_YCB.T


def load_ycbv_truth(root: str | Path, object_name: str | None, models: str | Path | None = None) -> Truth:
    """One object's truth in a YCB-Video video: poses of the frames that list it, its surface (``model.obj`` where the
    models folder has one, else its points), extents of its points' box, masks from the label images.

    ``models`` defaults to ``<root>/../models``. Raises InputError for an object the video does not hold.
    """
    root = Path(root)
    document = _poses_document(root)
    present = sorted({name for entry in document.values() if isinstance(entry, dict) for name in entry.get("objects", {})})
    if object_name not in present:
        raise InputError(root / "poses.json", f"object {object_name!r} is not in this video; it holds {', '.join(present)}")
    folder = Path(models) if models is not None else root.parent / "models"
    points_path = folder / object_name / "points.xyz"
    try:
        points = np.loadtxt(points_path, dtype=np.float64, ndmin=2)[:, :3]
    except (OSError, ValueError, IndexError) as error:
        raise InputError(points_path, f"cannot read the model's points ({error.__class__.__name__})") from error
    A, points_obj = _object_frame(points)
    mesh = None
    if (folder / object_name / "model.obj").is_file():
        loaded = trimesh.load(folder / object_name / "model.obj", force="mesh", process=False)
        vertices = (np.asarray(loaded.vertices, dtype=np.float64) - A[:3, 3]) @ SHAPENET_FROM_YCB.T
        mesh = trimesh.Trimesh(vertices, np.asarray(loaded.faces), process=False)
    poses = {}
    for frame_id, entry in document.items():  # frames: tens
        matrix = entry.get("objects", {}).get(object_name) if isinstance(entry, dict) else None
        if matrix is None:
            continue
        T = np.eye(4)
        T[:3, :] = np.asarray(matrix, dtype=np.float64).reshape(3, 4)
        U, _, Vt = np.linalg.svd(T[:3, :3])  # stored to single precision: the nearest rotation
        T[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        poses[str(frame_id)] = T @ A
    category = YCB_CATEGORIES.get(object_name, "other")
    label = YCB_CLASSES.index(object_name) + 1 if object_name in YCB_CLASSES else None
    camera = _camera(root / "poses.json", next(iter(document.values())))

    def mask(frame_id: str) -> np.ndarray:
        labels = read_labels(root / f"{frame_id}-label.png", camera)
        return labels == label if label is not None else np.zeros(labels.shape, bool)

    extents = points_obj.max(axis=0) - points_obj.min(axis=0)
    notes = {"source": "YCB-Video", "object": object_name, "models": str(folder)}
    return Truth(root, category, default_symmetry(category), extents, poses, mesh, notes, points=points_obj, masks=mask)


def ycbv_objects(root: str | Path) -> list[str]:
    """The objects a YCB-Video video's poses.json lists, sorted."""
    document = _poses_document(Path(root))
    return sorted({name for entry in document.values() if isinstance(entry, dict) for name in entry.get("objects", {})})
