"""A frame the smoothing bent far from its refined pose gets that pose back where it fits clearly better
(refine.undo_smoothing_bends): a rendered camera, its true poses as the refined ones, some frames bent."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_tracking_render import render_tracker

from annotate.tracking.quality import pose_difference
from annotate.tracking.refine import undo_smoothing_bends
from annotate.tracking.tracker import FrameResult


def _turned(pose: np.ndarray, deg: float) -> np.ndarray:
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 0.6, 0.8])).as_matrix()
    return pose @ turn


@pytest.mark.slow
def test_a_bent_frame_gets_its_refined_pose_back_only_where_that_fits_better(rendered_camera):
    sequence, mesh, truth = rendered_camera
    tracker = render_tracker(sequence, mesh)
    ids = sorted(truth)
    refined = {f: FrameResult(truth[f].copy(), True, {"fitness": 0.9}) for f in ids}
    smoothed = dict(refined)
    smoothed[ids[5]] = FrameResult(_turned(truth[ids[5]], 15.0), True, {"fitness": 0.9, "mark": 1})  # bent 15 deg
    smoothed[ids[7]] = FrameResult(_turned(truth[ids[7]], 2.0), True, {"fitness": 0.9})  # within the 3 deg let be
    smoothed[ids[3]] = FrameResult(_turned(truth[ids[3]], 60.0), True, {"fitness": 0.9})  # a flip's turn: not a bend
    # the refinement had frame 9 wrong, the smoothing right: the smoothed pose fits better and stays
    refined[ids[9]] = FrameResult(_turned(truth[ids[9]], 15.0), True, {"fitness": 0.9})
    out = undo_smoothing_bends(tracker, refined, smoothed, [ids[0]])
    assert pose_difference(out[ids[5]].pose, truth[ids[5]])[0] < 1e-9
    assert out[ids[5]].figures == {"fitness": 0.9, "mark": 1}, "the figures stay the smoothed frame's"
    assert out[ids[7]] is smoothed[ids[7]]
    assert out[ids[3]] is smoothed[ids[3]]
    assert out[ids[9]] is smoothed[ids[9]]
    assert all(out[f] is smoothed[f] for f in ids if f != ids[5])
    # off: nothing is undone
    off = undo_smoothing_bends(render_tracker(sequence, mesh, smoothing_undo_deg=0.0), refined, smoothed, [ids[0]])
    assert all(off[f] is smoothed[f] for f in ids)
