"""The data layer: RGB-D sequences in Redwood's layout, the camera, the annotation document, and
synthetic sequences with known truth. Imports none of the other parts."""

from .annotation import Annotation, FramePose, load_annotation, save_annotation, annotation_path
from .camera import Camera
from .errors import InputError
from .pointcloud import PointCloud, frame_points, in_oriented_box
from .reader import FrameFiles, Sequence, open_sequence, pair_frames

__all__ = [
    "Annotation", "FramePose", "load_annotation", "save_annotation", "annotation_path",
    "Camera", "InputError", "PointCloud", "frame_points", "in_oriented_box",
    "FrameFiles", "Sequence", "open_sequence", "pair_frames",
]
