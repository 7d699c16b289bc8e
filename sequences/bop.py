"""BOP's scene layout (bop_toolkit's docs/bop_datasets_format.md), read as a sequence with one truth per object.

A scene folder ``<dataset>/<split>/<scene id>/`` holds ``rgb/<image id>.png|jpg``, ``depth/<image id>.png``
(uint16; millimetres = value x depth_scale), ``scene_camera.json`` (per image: ``cam_K`` row-major 3x3,
``depth_scale``), ``scene_gt.json`` (per image: ``[{obj_id, cam_R_m2c (row-major 3x3), cam_t_m2c (mm)}]``)
and ``mask_visib/<image id>_<gt index>.png``. Models: ``<dataset>/models/obj_<obj id>.ply`` (millimetres).

BOP models carry no category and no agreed "up": a truth from BOP has category ``other``, symmetry
``none``, and keeps the model's own axes, centred on its box (metres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from .camera import Camera
from .documents import load_document
from .errors import InputError
from .images import read_labels
from .reader import COLOR_SUFFIXES, FrameFiles, Sequence
from .truth import Truth


def _json(path: Path, what: str) -> dict:
    data = load_document(path, what, as_yaml=False)
    if not isinstance(data, dict) or not data:
        raise InputError(path, f"{what} must be a non-empty mapping of image ids")
    return data


def _camera(path: Path, entry, width: int = 640, height: int = 480) -> Camera:
    """An image's camera: ``cam_K`` and ``depth_scale`` (BOP's: millimetres per unit)."""
    if not isinstance(entry, dict) or "cam_K" not in entry or "depth_scale" not in entry:
        raise InputError(path, "an image's cam_K or depth_scale is missing")
    try:
        millimetres = float(entry["depth_scale"])
    except (TypeError, ValueError) as error:
        raise InputError(path, f"an image's depth_scale is malformed ({error.__class__.__name__})") from error
    return Camera.from_matrix(path, entry["cam_K"], millimetres / 1000.0, width, height)


def open_bop_scene(root: str | Path) -> Sequence:
    """A BOP scene as a sequence: frames by image id (six digits), the camera of its first image.

    The image size is read from the first colour image (BOP datasets differ in it).
    """
    from .images import open_image

    root = Path(root)
    cameras = _json(root / "scene_camera.json", "scene_camera.json")
    frames = []
    for key in sorted(cameras, key=lambda k: int(k) if str(k).isdigit() else 0):  # image ids: thousands at most
        stem = f"{int(key):06d}" if str(key).isdigit() else str(key)
        colour = next((root / "rgb" / f"{stem}{suffix}" for suffix in COLOR_SUFFIXES if (root / "rgb" / f"{stem}{suffix}").is_file()), None)
        depth = root / "depth" / f"{stem}.png"
        if colour is not None and depth.is_file():
            frames.append(FrameFiles(stem, colour, depth))
    if not frames:
        raise InputError(root, "no image of scene_camera.json has both rgb/<id> and depth/<id>.png (BOP layout)")
    first_key = next(k for k in cameras if (f"{int(k):06d}" if str(k).isdigit() else str(k)) == frames[0].id)
    width, height = open_image(frames[0].color_path).size
    return Sequence.from_frames(root, frames, _camera(root / "scene_camera.json", cameras[first_key], width, height), "bop")


def _object_id(root: Path, object_name: str | None) -> int:
    text = str(object_name or "").removeprefix("obj_")
    if not text.isdigit():
        raise InputError(root / "scene_gt.json", f"name the object by its BOP id (obj_000001 or 1), got {object_name!r}")
    return int(text)


def load_bop_truth(root: str | Path, object_name: str | None, models: str | Path | None = None) -> Truth:
    """One object's truth in a BOP scene: the poses of its first instance per image, its model (millimetres to metres,
    centred on its box), and its visible masks. ``models`` defaults to ``<root>/../../models``."""
    root = Path(root)
    sequence = open_bop_scene(root)
    obj_id = _object_id(root, object_name)
    gt = _json(root / "scene_gt.json", "scene_gt.json")
    raw, instance = {}, {}
    for key, entries in gt.items():  # images: thousands at most
        stem = f"{int(key):06d}" if str(key).isdigit() else str(key)
        for index, entry in enumerate(entries if isinstance(entries, list) else []):
            if isinstance(entry, dict) and entry.get("obj_id") == obj_id:
                try:
                    T = np.eye(4)
                    T[:3, :3] = np.asarray(entry["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
                    T[:3, 3] = np.asarray(entry["cam_t_m2c"], dtype=np.float64).reshape(3) / 1000.0
                except (KeyError, TypeError, ValueError) as error:
                    raise InputError(root / "scene_gt.json", f"image {key}: a malformed pose ({error.__class__.__name__})") from error
                raw[stem], instance[stem] = T, index
                break
    if not raw:
        raise InputError(root / "scene_gt.json", f"object {obj_id} appears in no image of this scene")
    model_path = (Path(models) if models is not None else root.parent.parent / "models") / f"obj_{obj_id:06d}.ply"
    if not model_path.is_file():
        raise InputError(model_path, "the object's model file is missing")
    try:
        loaded = trimesh.load(model_path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many types for corrupt files
        raise InputError(model_path, f"cannot read the object's model ({error.__class__.__name__})") from error
    vertices = np.asarray(loaded.vertices, dtype=np.float64) / 1000.0
    centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    mesh = trimesh.Trimesh(vertices - centre, np.asarray(loaded.faces), process=False)
    offset = np.eye(4)
    offset[:3, 3] = centre  # the box-centred object frame in the model's frame
    poses = {stem: T @ offset for stem, T in raw.items()}

    def mask(frame_id: str) -> np.ndarray:
        path = root / "mask_visib" / f"{frame_id}_{instance[frame_id]:06d}.png"
        return read_labels(path, sequence.camera) > 127

    return Truth(root, "other", "none", mesh.extents.copy(), poses, mesh, {"source": "BOP", "obj_id": obj_id}, masks=mask)
