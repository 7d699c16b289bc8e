"""The data layer: RGB-D sequences in Redwood's layout, the camera, the annotation document, and
synthetic sequences with known truth. Imports none of the other parts.

The names below load their module on first use (PEP 562): importing one light submodule (``sequences.errors``,
``sequences.atomic``) does not pull in SciPy and PIL, which a command's client process may never need.
"""

from __future__ import annotations

from importlib import import_module

#: Public name -> the submodule that defines it.
_WHERE = {
    "Annotation": "annotation", "FramePose": "annotation", "load_annotation": "annotation", "save_annotation": "annotation",
    "annotation_path": "annotation", "Camera": "camera", "InputError": "errors", "PointCloud": "pointcloud",
    "frame_points": "pointcloud", "in_oriented_box": "pointcloud", "FrameFiles": "reader", "Sequence": "reader",
    "open_sequence": "reader", "pair_frames": "reader",
}

__all__ = list(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f".{_WHERE[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))
