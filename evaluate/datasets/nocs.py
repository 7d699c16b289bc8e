"""Reader of NOCS REAL275-format data (the sample in ``../shared/data/nocs_real_sample``).

Layout: ``ROOT/<split>/<scene>/<frame>_{color,depth,mask,meta}.png|txt``,
``ROOT/gts/<split>/results_<split>_<scene>_<frame>.pkl`` (``gt_RTs``: one 4x4 per valid
instance, in increasing instance id, with the scale, the box diagonal, folded into the rotation)
and ``ROOT/obj_models/<split>/<model>.obj`` (metres) with ``<model>.txt`` (the box's side lengths).
Frames without a ``gts`` file have no ground truth and give no samples.

Samples come out in ShapeNet axes, remapped as cpas_toolbox's ``real275.yaml`` does
(``remap_y_axis: y, remap_x_axis: -z``): ShapeNet x = NOCS z, y = y, z = -NOCS x.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np

from evaluate.geometry import matrix_to_quat
from sequences.annotation import default_symmetry
from sequences.axes import SHAPENET_FROM_NOCS
from sequences.camera import Camera
from sequences.errors import InputError
from sequences.names import check_name

from .base import Dataset, load_mesh_file
from .frames import read_instance_ids
from .sample import Sample

#: NOCS REAL275 camera (from NOCS's detect_eval.py, as cpas_toolbox's real275.yaml).
NOCS_CAMERA = Camera(fx=591.0125, fy=590.16775, cx=322.525, cy=244.11084, width=640, height=480, depth_scale=0.001)
#: NOCS class ids (meta.txt's second column); 0 is a distractor.
NOCS_CATEGORIES = {1: "bottle", 2: "bowl", 3: "camera", 4: "can", 5: "laptop", 6: "mug"}
BACKGROUND = 255
#: Rotation matrices whose columns' norms differ by more than this (relative) are not a scaled rotation.
SCALE_TOLERANCE = 1e-3


def decompose_scaled_rotation(path: Path, sRT: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Split a NOCS 4x4 ``sRT`` into (rotation (3, 3), scale, translation (3,)); InputError if it is not s*R."""
    sRT = np.asarray(sRT, dtype=np.float64)
    if sRT.shape != (4, 4) or not np.isfinite(sRT).all():
        raise InputError(path, f"gt_RTs entry must be a finite 4x4 matrix, got shape {sRT.shape}")
    sR = sRT[:3, :3]
    scales = np.linalg.norm(sR, axis=0)
    scale = float(scales.mean())
    if scale <= 0 or np.ptp(scales) > SCALE_TOLERANCE * scale:
        raise InputError(path, f"gt_RTs rotation part is not a uniformly scaled rotation (column norms {scales.round(6).tolist()})")
    R = sR / scale
    # nearest rotation (removes rounding in the stored matrix)
    U, _, Vt = np.linalg.svd(R)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    if np.linalg.det(sR) <= 0:
        raise InputError(path, "gt_RTs rotation part is a reflection")
    return R, scale, sRT[:3, 3].copy()


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles NumPy arrays and plain containers only: a results pickle must not run code."""

    def find_class(self, module: str, name: str):
        if module.split(".")[0] == "numpy":
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def load_gts(path: Path) -> dict:
    try:
        data = _NumpyOnlyUnpickler(io.BytesIO(path.read_bytes())).load()
    except OSError as error:
        raise InputError(path, f"cannot read ({error.__class__.__name__})") from error
    except Exception as error:
        raise InputError(path, f"not a NOCS results pickle ({error.__class__.__name__}: {error})") from error
    if not isinstance(data, dict) or "gt_RTs" not in data:
        raise InputError(path, "no gt_RTs in the results pickle")
    return data


def handle_visibility(path: Path, gts: dict, n: int) -> list[bool] | None:
    """``gt_handle_visibility`` of a results pickle (one 0/1 per ``gt_RTs`` entry; NOCS's evaluation reads
    it for mugs), or None when the pickle has none."""
    value = gts.get("gt_handle_visibility")
    if value is None:
        return None
    flags = np.asarray(value).reshape(-1)
    if len(flags) != n or flags.dtype.kind not in "biuf" or not np.isin(flags, (0, 1)).all():
        raise InputError(path, f"gt_handle_visibility must hold one 0 or 1 per gt_RTs entry ({n}), got {np.asarray(value).tolist()!r}"[:300])
    return [bool(f) for f in flags]


def read_meta(path: Path) -> dict[int, tuple[int, str]]:
    """meta.txt: {instance id: (class id, model name)}."""
    rows = {}
    try:
        lines = path.read_text().splitlines()
    except OSError as error:
        raise InputError(path, f"cannot read ({error.__class__.__name__})") from error
    for number, line in enumerate(lines, 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 3 or not parts[0].isdigit() or not parts[1].isdigit():
            raise InputError(path, f"line {number}: expected '<instance id> <class id> <model name>'")
        rows[int(parts[0])] = (int(parts[1]), check_name(parts[2], f"line {number}: model name", path))  # a name, not a path
    return rows


def read_extents(path: Path) -> np.ndarray:
    """``<model>.txt``: the model's box side lengths (m), one number a line or three on one line."""
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except OSError as error:
        raise InputError(path, f"cannot read ({error.__class__.__name__})") from error
    except ValueError as error:
        raise InputError(path, "expected three numbers (box side lengths, metres)") from error
    if values.shape != (3,) or not np.isfinite(values).all() or (values <= 0).any():
        raise InputError(path, "expected three positive numbers (box side lengths, metres)")
    return values


class NocsDataset(Dataset):
    """NOCS REAL275-format frames with ground-truth poses, one sample per annotated instance."""

    name = "nocs"

    def __init__(self, root: str | Path, splits: tuple[str, ...] = ("real_test", "real_train")) -> None:
        root = Path(root)
        if not root.is_dir():
            raise InputError(root, "NOCS dataset folder not found")
        samples: list[Sample] = []
        self.frames_without_truth: list[str] = []
        for split in splits:
            for color in sorted((root / split).glob("*/*_color.png")):
                samples.extend(self._frame_samples(root, split, color))
        if not samples:
            raise InputError(root, "no NOCS frame with ground truth (gts/<split>/results_*.pkl) found")
        super().__init__(samples, root)
        self.name = root.name or self.name

    def _frame_samples(self, root: Path, split: str, color: Path) -> list[Sample]:
        scene, frame = color.parent.name, color.name[: -len("_color.png")]
        gts_path = root / "gts" / split / f"results_{split}_{scene}_{frame}.pkl"
        if not gts_path.is_file():
            self.frames_without_truth.append(f"{split}/{scene}/{frame}")
            return []
        mask_path = color.with_name(f"{frame}_mask.png")
        meta = read_meta(color.with_name(f"{frame}_meta.txt"))
        gts = load_gts(gts_path)
        gt_RTs = np.asarray(gts["gt_RTs"])
        handles = handle_visibility(gts_path, gts, len(gt_RTs))
        ids = np.unique(read_instance_ids(mask_path, NOCS_CAMERA))
        ids = [int(i) for i in ids if i != BACKGROUND]
        samples, gt_index = [], 0
        for instance in ids:
            if instance not in meta:
                raise InputError(mask_path, f"instance {instance} is not listed in {frame}_meta.txt")
            class_id, model = meta[instance]
            if class_id == 0:  # distractor: not in gt_RTs
                continue
            if class_id not in NOCS_CATEGORIES:
                raise InputError(color.with_name(f"{frame}_meta.txt"), f"unknown class id {class_id}")
            if gt_index >= len(gt_RTs):
                raise InputError(gts_path, f"gt_RTs has {len(gt_RTs)} entries but the mask has more annotated instances")
            R, _, t = decompose_scaled_rotation(gts_path, gt_RTs[gt_index])
            handle_visible = None if handles is None else handles[gt_index]
            gt_index += 1
            model_dir = root / "obj_models" / split
            extents = read_extents(model_dir / f"{model}.txt")
            mesh_path = model_dir / f"{model}.obj"
            category = NOCS_CATEGORIES[class_id]
            samples.append(
                Sample(
                    dataset=self.name,
                    sequence=f"{split}/{scene}",
                    frame=frame,
                    instance=str(instance),
                    category=category,
                    symmetry=default_symmetry(category),
                    position=t,
                    orientation=matrix_to_quat(R @ SHAPENET_FROM_NOCS.T),
                    extents=np.abs(SHAPENET_FROM_NOCS @ extents),
                    camera=NOCS_CAMERA,
                    color_path=color,
                    depth_path=color.with_name(f"{frame}_depth.png"),
                    mesh_path=mesh_path if mesh_path.is_file() else None,
                    mask_path=mask_path,
                    handle_visible=handle_visible,
                )
            )
        return samples

    def _load_mesh(self, path: Path):
        mesh = load_mesh_file(path)
        # the mesh's box is centred on the origin; recentre anyway so the box convention holds exactly
        lo, hi = mesh.bounds
        mesh.vertices = (np.asarray(mesh.vertices) - (lo + hi) / 2) @ SHAPENET_FROM_NOCS.T
        return mesh

    def mask(self, sample: Sample, depth: np.ndarray | None = None) -> np.ndarray:
        """The dataset's own instance mask."""
        return read_instance_ids(sample.mask_path, sample.camera) == int(sample.instance)
