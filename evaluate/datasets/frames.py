"""Reading one frame's colour, depth and instance-mask images, with one-line errors (see :mod:`sequences.images`)."""

from sequences.images import read_color, read_depth
from sequences.images import read_labels as read_instance_ids

__all__ = ["read_color", "read_depth", "read_instance_ids"]
