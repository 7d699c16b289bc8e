"""Runs a cpas_toolbox method class unchanged (the ``CPASMethod`` interface of cpas_toolbox 1.0).

The wrapped class is constructed as ``cls(config: dict, camera: cpas_toolbox.camera_utils.Camera)``
and called as ``inference(color_image, depth_image, instance_mask, category_str)`` with torch
tensors: colour (H, W, 3) float RGB in 0..1, depth (H, W) float metres, mask (H, W) bool. It returns
a dict with ``position`` (3,) (OpenCV camera, m), ``orientation`` (4,) x, y, z, w, ``extents`` (3,)
(m), ``reconstructed_pointcloud`` (N, 3) and ``reconstructed_mesh`` (an open3d TriangleMesh), both in
the object frame, metres, either may be None. Both use the same camera and object conventions as
ours (cpas_toolbox evaluates in ShapeNet axes, OpenCV camera). As cpas_toolbox's own evaluation
does, the point cloud is the reconstruction used for shape metrics; the mesh only when there is no
point cloud.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from sequences.camera import Camera

from .base import Method, Prediction
from .sample_method import PredictionFailure


def cpas_camera(camera: Camera):
    """Our camera as a cpas_toolbox ``Camera`` (pixel centres at integer coordinates, as ours).
    Without cpas_toolbox, a stand-in with the same attributes."""
    values = dict(width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy)
    try:
        from cpas_toolbox.camera_utils import Camera as CpasCamera
    except ImportError:
        return SimpleNamespace(**values, s=0.0, pixel_center=0.0)
    return CpasCamera(**values, s=0.0, pixel_center=0.0)


def _array(value: Any, field: str) -> np.ndarray:
    if value is None:
        raise PredictionFailure(f"cpas method returned no {field}")
    if hasattr(value, "detach"):  # a torch tensor
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float64)


class CpasMethodAdapter(Method):
    """A :class:`Method` around a class with cpas_toolbox's CPASMethod signature."""

    def __init__(self, cls: type, config: dict | None, camera: Camera) -> None:
        self.cls = cls
        self.name = getattr(cls, "__name__", "cpas_method")
        self.camera = camera
        self.wrapped = cls(config=dict(config or {}), camera=cpas_camera(camera))

    def inference(self, color: np.ndarray, depth: np.ndarray, mask: np.ndarray, category: str, camera: Camera) -> Prediction:
        import torch

        if camera != self.camera:
            # cpas methods take the camera once, at construction
            raise PredictionFailure(f"sample camera {camera} differs from the one {self.name} was built with")
        result = self.wrapped.inference(
            color_image=torch.from_numpy(np.ascontiguousarray(color, dtype=np.float32) / 255.0),
            depth_image=torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32)),
            instance_mask=torch.from_numpy(np.ascontiguousarray(mask, dtype=bool)),
            category_str=category,
        )
        if not isinstance(result, dict):
            raise PredictionFailure(f"cpas method returned {type(result).__name__}, not a dict")
        reconstruction = None
        if result.get("reconstructed_pointcloud") is not None:
            reconstruction = _array(result["reconstructed_pointcloud"], "reconstructed_pointcloud")
        elif result.get("reconstructed_mesh") is not None:
            reconstruction = _trimesh(result["reconstructed_mesh"])
        return Prediction(
            _array(result.get("position"), "position").reshape(-1),
            _array(result.get("orientation"), "orientation").reshape(-1),
            _array(result.get("extents"), "extents").reshape(-1),
            reconstruction,
        )


def _trimesh(mesh):
    """An open3d TriangleMesh (or anything with vertices and triangles/faces) as a trimesh.Trimesh."""
    import trimesh

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(getattr(mesh, "triangles", None) if hasattr(mesh, "triangles") else mesh.faces)
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
