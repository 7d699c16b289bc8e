"""What every dataset reader offers the evaluation: samples, and per sample its images, mask and mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evaluate.geometry import transform
from sequences.errors import InputError

from .frames import read_color, read_depth
from .masks import box_mesh, render_depth, visible_mask
from .sample import Sample


class Dataset:
    """A list of :class:`Sample` with lazy access to frames and meshes (meshes cached per file)."""

    name: str = "dataset"

    def __init__(self, samples: list[Sample], root: Path) -> None:
        self.samples = samples
        self.root = Path(root)
        self._mesh_cache: dict[Path, object] = {}

    def __len__(self) -> int:
        return len(self.samples)

    def __iter__(self):
        return iter(self.samples)

    @property
    def categories(self) -> list[str]:
        """Categories present, sorted."""
        return sorted({s.category for s in self.samples})

    def mesh(self, sample: Sample):
        """The sample's true mesh (trimesh.Trimesh, ShapeNet axes, metres, box-centred), or None without one."""
        if sample.mesh_path is None:
            return None
        if sample.mesh_path not in self._mesh_cache:
            self._mesh_cache[sample.mesh_path] = self._load_mesh(sample.mesh_path)
        return self._mesh_cache[sample.mesh_path]

    def _load_mesh(self, path: Path):
        raise NotImplementedError

    def color(self, sample: Sample) -> np.ndarray:
        """(H, W, 3) uint8 RGB."""
        return read_color(self._frame_path(sample, "color"), sample.camera)

    def depth(self, sample: Sample) -> np.ndarray:
        """(H, W) float32 metres, 0 = no measurement."""
        return read_depth(self._frame_path(sample, "depth"), sample.camera)

    def mask(self, sample: Sample, depth: np.ndarray | None = None) -> np.ndarray:
        """(H, W) bool instance mask: the posed true mesh (its box where there is no mesh), ray-cast,
        minus pixels where the observed depth lies more than 1 cm in front (cpas_toolbox's rule)."""
        mesh = self.mesh(sample)
        if mesh is not None:
            vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        else:
            vertices, faces = box_mesh(sample.extents)
        rendered = render_depth(transform(sample.pose, vertices), faces, sample.camera)
        return visible_mask(rendered, depth)

    def _frame_path(self, sample: Sample, kind: str) -> Path:
        path = sample.color_path if kind == "color" else sample.depth_path
        if path is None:
            raise InputError(self.root, f"no {kind} frame for sample {sample.label}: give the frames' root with --frames")
        return path


def load_mesh_file(path: Path):
    """Read a triangle mesh (any format trimesh reads) without altering vertices; InputError when unreadable."""
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except FileNotFoundError as error:
        raise InputError(path, "mesh file not found") from error
    except Exception as error:  # trimesh raises many types on corrupt files
        raise InputError(path, f"unreadable mesh ({error.__class__.__name__}: {error})") from error
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "mesh has no triangles")
    if not np.isfinite(mesh.vertices).all():
        raise InputError(path, "mesh has non-finite vertices")
    return mesh
