"""Reader of BOP-format datasets (bop_toolkit's ``docs/bop_datasets_format.md``), as ``reconstruct-sequence
--format bop`` writes them, as samples in ShapeNet axes.

Layout: ``ROOT/models/models_info.json`` and ``ROOT/models/obj_<obj id>.ply`` (millimetres), and scenes
``ROOT/<split>/<scene id>/`` with ``scene_camera.json``, ``scene_gt.json``, ``rgb/``, ``depth/`` and
``mask_visib/<image id>_<gt index>.png``. One sample per annotated instance.

Conversions: the model frame is the document's (z up, origin at the centre of the model's box), turned into
ShapeNet axes by ``sequences.bop.SHAPENET_FROM_BOP``; the box is the models_info box (``min``, ``size``), and a
model whose origin is off its box centre is re-centred (the position is the box centre, R c + t). A continuous
symmetry about the model's z axis (y in ShapeNet axes) gives ``symmetry: y``. Millimetres become metres.

Names: where ``ROOT/annotations.json`` is our export's index, a sample's sequence and frame are the exported
sequence's name and frame id, its category the document's, and it has no instance (one object per scene, as
in REDWOOD75: a predictions file keyed for the REDWOOD75 export of the same sequences fits this one too).
Elsewhere the sequence is ``<split>/<scene id>``, the frame the image id (six digits), the instance the
ground-truth index, and the category ``other`` (BOP models have none).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evaluate.geometry import matrix_to_quat
from sequences.bop import MM, SHAPENET_FROM_BOP, read_models_info, read_scene_camera, read_scene_gt
from sequences.camera import Camera
from sequences.documents import load_document
from sequences.errors import InputError
from sequences.images import open_image
from sequences.names import check_name

from .base import Dataset, load_mesh_file
from .frames import read_instance_ids
from .sample import Sample

#: Where our export keeps its index of sequences (the export's commit point, reconstruct.export_index).
INDEX = "annotations.json"
#: A continuous symmetry whose axis is within this (cosine) of the model's z axis counts as "symmetry: y".
AXIS_COSINE = 0.999


def _index(root: Path) -> dict[tuple[str, int], dict]:
    """Our export's index by (split, scene id): {"sequence", "category", "images": {image id: frame id}}; empty elsewhere."""
    path = root / INDEX
    if not path.is_file():
        return {}
    data = load_document(path, "BOP export index", as_yaml=False)
    if not isinstance(data, dict):
        raise InputError(path, "expected a mapping of sequences")
    out = {}
    for sequence, entry in data.items():
        if not isinstance(entry, dict) or entry.get("format") != "bop":
            raise InputError(path, f"sequence {sequence!r} is not a BOP export entry (a REDWOOD75 annotations.json in a BOP folder?)")
        images = entry.get("images")
        if not isinstance(entry.get("scene_id"), int) or not isinstance(images, dict) or not isinstance(entry.get("split"), str):
            raise InputError(path, f"sequence {sequence!r}: needs split, scene_id and images")
        out[(check_name(entry["split"], "split", path), entry["scene_id"])] = {
            "sequence": check_name(sequence, "sequence name", path),
            "category": str(entry.get("category", "other")),
            "images": {int(k): check_name(v, "frame id", path) for k, v in images.items() if str(k).isdigit()},
        }
    return out


class BopDataset(Dataset):
    """BOP scenes with their ground-truth poses, one sample per annotated instance, in ShapeNet axes."""

    name = "bop"

    def __init__(self, root: str | Path) -> None:
        root = Path(root)
        info_path = root / "models" / "models_info.json"
        if not info_path.is_file():
            raise InputError(info_path, "not found (a BOP dataset folder holds models/models_info.json and its scenes)")
        self.models = read_models_info(info_path)
        index = _index(root)
        samples: list[Sample] = []
        scenes = sorted(p.parent for p in root.glob("*/*/scene_gt.json") if p.parent.name.isdigit())
        for scene in scenes:  # a few scenes per sequence at most
            samples.extend(self._scene_samples(root, scene, index.get((scene.parent.name, int(scene.name)))))
        if not samples:
            raise InputError(root, "no BOP scene with ground truth (<split>/<scene id>/scene_gt.json) found")
        super().__init__(samples, root)
        self.name = root.name or self.name

    def _scene_samples(self, root: Path, scene: Path, ours: dict | None) -> list[Sample]:
        cameras = read_scene_camera(scene / "scene_camera.json")
        gts = read_scene_gt(scene / "scene_gt.json")
        samples = []
        size: tuple[int, int] | None = None
        for im_id in sorted(gts):
            if im_id not in cameras:
                raise InputError(scene / "scene_camera.json", f"image {im_id} of scene_gt.json has no camera")
            color = next((p for p in (scene / "rgb" / f"{im_id:06d}{s}" for s in (".png", ".jpg")) if p.is_file()), None)
            depth = scene / "depth" / f"{im_id:06d}.png"
            if size is None and color is not None:
                size = open_image(color).size  # the scene's images share one size
            width, height = size or (640, 480)
            K = cameras[im_id]["cam_K"]
            camera = Camera.from_matrix(scene / "scene_camera.json", K, cameras[im_id]["depth_scale"] / MM, width, height)
            for gt_index, gt in enumerate(gts[im_id]):
                model = self.models.get(gt["obj_id"])
                if model is None:
                    raise InputError(root / "models" / "models_info.json", f"object {gt['obj_id']} of {scene / 'scene_gt.json'} is not listed")
                centre = (model["min"] + model["size"] / 2) / MM  # the box centre, model frame, m
                R = gt["cam_R_m2c"]
                mesh_path = root / "models" / f"obj_{gt['obj_id']:06d}.ply"
                mask_path = scene / "mask_visib" / f"{im_id:06d}_{gt_index:06d}.png"
                samples.append(
                    Sample(
                        dataset=self.name,
                        sequence=ours["sequence"] if ours else f"{scene.parent.name}/{scene.name}",
                        frame=ours["images"].get(im_id, f"{im_id:06d}") if ours else f"{im_id:06d}",
                        instance=None if ours else str(gt_index),
                        category=ours["category"] if ours else "other",
                        symmetry=self.symmetry(gt["obj_id"]),
                        position=R @ centre + gt["cam_t_m2c"] / MM,
                        orientation=matrix_to_quat(R @ SHAPENET_FROM_BOP.T),
                        extents=np.abs(SHAPENET_FROM_BOP @ model["size"]) / MM,
                        camera=camera,
                        color_path=color,
                        depth_path=depth if depth.is_file() else None,
                        mesh_path=mesh_path if mesh_path.is_file() else None,
                        mask_path=mask_path if mask_path.is_file() else None,
                    )
                )
        return samples

    def symmetry(self, obj_id: int) -> str:
        """"y" where the model has a continuous symmetry about its z axis through its box centre, else "none"."""
        model = self.models[obj_id]
        centre = model["min"] + model["size"] / 2
        for sym in model["symmetries_continuous"]:
            axis = sym["axis"] / max(np.linalg.norm(sym["axis"]), 1e-12)
            off = sym["offset"] - centre
            if abs(axis[2]) >= AXIS_COSINE and np.linalg.norm(off - (off @ axis) * axis) <= 1e-3 * model["diameter"]:
                return "y"
        return "none"

    def mask(self, sample: Sample, depth: np.ndarray | None = None) -> np.ndarray:
        """The dataset's visible mask (``mask_visib``, non-zero = object) where there is one, else the posed mesh ray-cast."""
        if sample.mask_path is not None:
            return read_instance_ids(sample.mask_path, sample.camera) > 0
        return super().mask(sample, depth)

    def _load_mesh(self, path: Path):
        mesh = load_mesh_file(path)
        vertices = np.asarray(mesh.vertices, dtype=np.float64) / MM
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        # box-centred, ShapeNet axes: a proper rotation, so faces keep their winding
        mesh.vertices = (vertices - (lo + hi) / 2) @ SHAPENET_FROM_BOP.T
        return mesh
