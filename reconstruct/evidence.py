"""The evidence hull: what carving left that a measured surface bounds, without the unseen space beside it.

Carving keeps every voxel never seen free: besides the object, space that no frame could see into
(a mug's lower inside hidden by its wall in every frame, the gap a hand held still in front of the
object for a whole grasp). A voxel is *backed* when some frame saw it just behind its measured
surface (0 to one tolerance deep; :class:`reconstruct.carving.CarveResult` counts them): the
object's surface is near it. The evidence hull keeps the backed voxels and what they enclose (the
inside of a solid object, deeper than one tolerance under every surface, is backed by none but is
walled in by backed voxels); unseen space that reaches carved space without crossing a backed voxel
goes.

Where part of the object's own surface was never seen, its voxels are unbacked too and the hull
loses them (a mug's handle cut off its body, the far half of an object seen from one side only):
so the hull may open space inside the carved outline, never move the outline. When the box of its
largest piece is not that of the carving's (within DEFAULT_BOX_SLACK), the carved occupancy is kept.
Hand remnants the hand's own surface backs stay either way.

Not applied by default (``reconstruct_sequence(evidence_hull=True)`` turns it on): measured on the benchmark's
dev split from the true poses, it opens the unseen inside of an open container (a mug whose inside no frame
saw: posed F@5mm 0.92 -> 1.00) but drains solid objects one of whose faces no frame measured (a camera 0.94 ->
0.79, a wood block 1.00 -> 0.81), and nothing in the data tells the two apart reliably. What stays of unseen
space is labelled so instead (:mod:`reconstruct.seen`).
"""

from __future__ import annotations

import numpy as np

from .meshing import fill_holes, largest_component

#: Voxels the hull's box may lie inside the carving's box on any side: a hull that only opens the inside keeps
#: the outline to a voxel; one that loses a part never seen (a mug's handle, a can's far half) moves it further.
DEFAULT_BOX_SLACK = 1


def voxel_box(mask: np.ndarray) -> np.ndarray:
    """(3, 2) int: the first and last index along each axis of the set voxels of a non-empty boolean grid."""
    return np.array([np.flatnonzero(mask.any(axis=tuple(b for b in range(3) if b != a)))[[0, -1]] for a in range(3)])


def evidence_hull(occupied: np.ndarray, behind_count: np.ndarray, box_slack: int = DEFAULT_BOX_SLACK) -> np.ndarray:
    """(nx, ny, nz) bool: the backed voxels of ``occupied`` with the space they enclose, or ``occupied`` where that moves the outline.

    ``behind_count`` (nx, ny, nz): frames that saw each voxel just behind the measured surface.
    The outline moves when the box of the hull's largest piece differs from that of
    ``occupied``'s by more than ``box_slack`` voxels on a side.
    """
    hull = fill_holes(occupied & (behind_count > 0))
    carved = largest_component(occupied)
    if not hull.any() or not carved.any():
        return occupied
    if np.abs(voxel_box(largest_component(hull)) - voxel_box(carved)).max() > box_slack:
        return occupied
    return hull
