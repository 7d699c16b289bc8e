"""BOP's scene layout (bop_toolkit's docs/bop_datasets_format.md), read as a sequence with one truth per object.

A scene folder ``<dataset>/<split>/<scene id>/`` holds ``rgb/<image id>.png|jpg``, ``depth/<image id>.png``
(uint16; millimetres = value x depth_scale), ``scene_camera.json`` (per image: ``cam_K`` row-major 3x3,
``depth_scale``), ``scene_gt.json`` (per image: ``[{obj_id, cam_R_m2c (row-major 3x3), cam_t_m2c (mm)}]``)
and ``mask_visib/<image id>_<gt index>.png``. Models: ``<dataset>/models/obj_<obj id>.ply`` (millimetres).

BOP models carry no category and no agreed "up": a truth from BOP has category ``other``, symmetry
``none``, and keeps the model's own axes, centred on its box (metres).

The readers below (:func:`read_scene_camera`, :func:`read_scene_gt`, :func:`read_scene_gt_info`,
:func:`read_models_info`) check one file each field by field, as the format document defines it, and return
plain numbers (NumPy arrays; millimetres as in the files); ``evaluate.datasets.bop`` and the tests use them.
The document puts the model frame's z axis up (an object standing upright) and its origin at the centre of
the model's box: :data:`SHAPENET_FROM_BOP` turns that frame into the toolkit's (ShapeNet, y up).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from .axes import SHAPENET_FROM_YCB
from .camera import Camera
from .documents import load_document
from .errors import InputError
from .images import read_labels
from .reader import COLOR_SUFFIXES, FrameFiles, Sequence
from .truth import Truth


#: ShapeNet coordinates from BOP model coordinates (z up, as the format document's "Coordinate systems" says):
#: ShapeNet x = BOP x, y = BOP z, z = -BOP y; the same proper rotation as YCB's models (also z up).
SHAPENET_FROM_BOP = SHAPENET_FROM_YCB
#: Millimetres per metre: BOP's models, translations and depth (after ``depth_scale``) are in millimetres.
MM = 1000.0
#: The fields of each file, as the format document lists them (optional ones of scene_camera.json aside).
SCENE_CAMERA_FIELDS = ("cam_K", "depth_scale")
SCENE_GT_FIELDS = ("obj_id", "cam_R_m2c", "cam_t_m2c")
SCENE_GT_INFO_FIELDS = ("bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract")
MODEL_INFO_FIELDS = ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z")


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


def _image_id(path: Path, key) -> int:
    if not (isinstance(key, str) and key.isdigit()):
        raise InputError(path, f"key {key!r} is not an image or object id (a non-negative integer)")
    return int(key)


def _numbers(path: Path, where: str, value, n: int) -> np.ndarray:
    """``value`` as n finite floats (a flat JSON list), else InputError naming the file and the field."""
    if not isinstance(value, list) or len(value) != n or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise InputError(path, f"{where}: expected a list of {n} numbers"[:200])
    array = np.asarray(value, dtype=np.float64)
    if not np.isfinite(array).all():
        raise InputError(path, f"{where}: non-finite value")
    return array


def read_scene_camera(path: str | Path) -> dict[int, dict]:
    """``scene_camera.json``: image id -> ``{"cam_K": (3, 3) pixels (saved row-wise), "depth_scale": mm per unit}``."""
    path = Path(path)
    out = {}
    for key, entry in _json(path, "scene_camera.json").items():
        im_id = _image_id(path, key)
        if not isinstance(entry, dict) or any(f not in entry for f in SCENE_CAMERA_FIELDS):
            raise InputError(path, f"image {key}: needs {' and '.join(SCENE_CAMERA_FIELDS)}")
        scale = _numbers(path, f"image {key}: depth_scale", [entry["depth_scale"]], 1)[0]
        if scale <= 0:
            raise InputError(path, f"image {key}: depth_scale must be positive")
        out[im_id] = {"cam_K": _numbers(path, f"image {key}: cam_K", entry["cam_K"], 9).reshape(3, 3), "depth_scale": float(scale)}
    return out


def read_scene_gt(path: str | Path) -> dict[int, list[dict]]:
    """``scene_gt.json``: image id -> per instance ``{"obj_id", "cam_R_m2c": (3, 3) (saved row-wise), "cam_t_m2c": (3,) mm}``."""
    path = Path(path)
    out = {}
    for key, entries in _json(path, "scene_gt.json").items():
        im_id = _image_id(path, key)
        if not isinstance(entries, list):
            raise InputError(path, f"image {key}: expected a list of instances")
        rows = []
        for index, entry in enumerate(entries):
            where = f"image {key}, instance {index}"
            if not isinstance(entry, dict) or any(f not in entry for f in SCENE_GT_FIELDS):
                raise InputError(path, f"{where}: needs {', '.join(SCENE_GT_FIELDS)}")
            if not isinstance(entry["obj_id"], int) or isinstance(entry["obj_id"], bool) or entry["obj_id"] < 0:
                raise InputError(path, f"{where}: obj_id must be a non-negative integer")
            R = _numbers(path, f"{where}: cam_R_m2c", entry["cam_R_m2c"], 9).reshape(3, 3)
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) <= 0:
                raise InputError(path, f"{where}: cam_R_m2c is not a rotation matrix")
            rows.append({"obj_id": entry["obj_id"], "cam_R_m2c": R, "cam_t_m2c": _numbers(path, f"{where}: cam_t_m2c", entry["cam_t_m2c"], 3)})
        out[im_id] = rows
    return out


def read_scene_gt_info(path: str | Path) -> dict[int, list[dict]]:
    """``scene_gt_info.json``: image id -> per instance the six fields of :data:`SCENE_GT_INFO_FIELDS` (boxes
    ``[x, y, width, height]`` in pixels, counts in pixels, ``visib_fract`` in [0, 1])."""
    path = Path(path)
    out = {}
    for key, entries in _json(path, "scene_gt_info.json").items():
        im_id = _image_id(path, key)
        if not isinstance(entries, list) or not all(isinstance(e, dict) and all(f in e for f in SCENE_GT_INFO_FIELDS) for e in entries):
            raise InputError(path, f"image {key}: every instance needs {', '.join(SCENE_GT_INFO_FIELDS)}")
        out[im_id] = [{f: e[f] for f in SCENE_GT_INFO_FIELDS} for e in entries]
    return out


def read_models_info(path: str | Path) -> dict[int, dict]:
    """``models_info.json``: object id -> ``{"diameter", "min": (3,), "size": (3,)}`` in mm, plus the symmetries as
    given (``symmetries_continuous``: ``[{"axis": (3,), "offset": (3,) mm}]``, ``symmetries_discrete``: 4x4s)."""
    path = Path(path)
    out = {}
    for key, entry in _json(path, "models_info.json").items():
        obj_id = _image_id(path, key)
        if not isinstance(entry, dict) or any(f not in entry for f in MODEL_INFO_FIELDS):
            raise InputError(path, f"object {key}: needs {', '.join(MODEL_INFO_FIELDS)}")
        values = _numbers(path, f"object {key}", [entry[f] for f in MODEL_INFO_FIELDS], len(MODEL_INFO_FIELDS))
        if values[0] <= 0 or (values[4:] <= 0).any():
            raise InputError(path, f"object {key}: diameter and sizes must be positive")
        continuous = entry.get("symmetries_continuous", [])
        if not isinstance(continuous, list) or not all(isinstance(c, dict) and "axis" in c and "offset" in c for c in continuous):
            raise InputError(path, f"object {key}: symmetries_continuous must be a list of {{axis, offset}}")
        out[obj_id] = {
            "diameter": float(values[0]),
            "min": values[1:4],
            "size": values[4:7],
            "symmetries_continuous": [{"axis": _numbers(path, f"object {key}: axis", c["axis"], 3),
                                       "offset": _numbers(path, f"object {key}: offset", c["offset"], 3)} for c in continuous],
            "symmetries_discrete": entry.get("symmetries_discrete", []),
        }
    return out
