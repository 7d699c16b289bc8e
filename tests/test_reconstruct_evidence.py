"""reconstruct.evidence: the evidence hull on voxel scenes whose backed and unseen parts are known by construction."""

from __future__ import annotations

import numpy as np

from reconstruct.evidence import evidence_hull


def _cup(n: int = 20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A square cup open at +y (walls and floor 2 voxels thick, all backed), a solid block (its
    2-voxel shell backed, its core not) beside it, and an unseen wedge that fills part of the cup's
    inside from the floor up (never seen: unbacked). Returns (occupied, behind counts, wedge)."""
    occupied = np.zeros((n, n, 2 * n), bool)
    backed = np.zeros_like(occupied)
    occupied[2:18, 2:18, 2:18] = True  # the cup's outside
    occupied[4:16, 4:18, 4:16] = False  # its inside, open at the top (y >= 4)
    backed |= occupied
    wedge = np.zeros_like(occupied)
    wedge[4:16, 4:12, 4:8] = True  # in the cup, against one wall and the floor
    occupied |= wedge
    occupied[2:18, 2:18, 20:36] = True  # the block
    backed[2:18, 2:18, 20:36] = True
    backed[4:16, 4:16, 22:34] = False  # its core: deeper than any frame's tolerance, never "behind"
    occupied[2:18, 2:4, 18:20] = True  # the block joins the cup along its base (one object)
    backed[2:18, 2:4, 18:20] = True
    behind = np.where(backed, 3, 0).astype(np.uint16)
    return occupied, behind, wedge


def test_unseen_space_open_to_carved_space_goes_and_enclosed_core_stays():
    occupied, behind, wedge = _cup()
    hull = evidence_hull(occupied, behind)
    np.testing.assert_array_equal(hull, occupied & ~wedge)
    assert hull[4:16, 4:16, 22:34].all()  # the unbacked core is walled in by backed voxels: kept


def test_hull_that_moves_the_outline_keeps_the_carved_occupancy():
    occupied, behind, _ = _cup()
    behind[2:18, 2:4, 18:20] = 0  # the join was never seen: the block and the cup are two pieces
    np.testing.assert_array_equal(evidence_hull(occupied, behind), occupied)
    occupied, behind, _ = _cup()
    behind[2:18, 2:18, 34:36] = 0  # the block's far face never seen: its core leaks out and the box shrinks
    np.testing.assert_array_equal(evidence_hull(occupied, behind), occupied)
    # a stray backed voxel outside the object does not move the outline
    occupied, behind, wedge = _cup()
    occupied[0, 0, 39] = True
    behind[0, 0, 39] = 1
    hull = evidence_hull(occupied, behind)
    np.testing.assert_array_equal(hull, occupied & ~wedge)


def test_nothing_backed_keeps_the_carved_occupancy():
    occupied, behind, _ = _cup()
    np.testing.assert_array_equal(evidence_hull(occupied, np.zeros_like(behind)), occupied)
