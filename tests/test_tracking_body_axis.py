"""A mug's box turned upright onto its body's axis fitted to the model (engine._snap_body_axis), on a rendered mug."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_tracking_render import mug_mesh, render_tracker, rendered_scene

from annotate.tracking.engine import _snap_body_axis
from annotate.tracking.refine import build_model

FRAMES = 16


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return rendered_scene(tmp_path_factory.mktemp("body_axis") / "mug_0004", mug_mesh(), frames=FRAMES, seed=5, hand=False)



def _tilted(deg: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.array([0.6, 0.0, 0.8])).as_matrix()
    return T


@pytest.mark.slow
def test_boxes_tilted_off_the_body_axis_are_turned_back_about_their_centre(scene):
    _, _, truth = scene
    ids = sorted(truth)
    # every box tilted 3 deg (as the placed boxes' mean error leaves it): the model's body axis is off their y
    poses = {f: truth[f] @ _tilted(3.0) for f in ids}
    tracker = render_tracker(*scene[:2])
    snap = _snap_body_axis(tracker, build_model(tracker, poses, tracker.config.max_global_frames, [ids[0], ids[-1]]))
    assert snap is not None
    assert np.array_equal(snap[:3, 3], np.zeros(3)), "the centre stays: the handle keeps it off the body's axis"
    # measured: 0.20 deg from the true tilt left, against 3 before
    left = [np.degrees(np.arccos(np.clip((poses[f] @ snap)[:3, 1] @ truth[f][:3, 1], -1, 1))) for f in ids]
    assert max(left) < 0.5, left
    # the correction is a tilt: the spin about the axis is not what it fixes, and it stays within the tilt's size
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(snap[:3, :3]).as_rotvec())) < 3.5


def test_no_snap_where_the_axis_fit_is_too_ill_conditioned(scene):
    _, _, truth = scene
    ids = sorted(truth)
    # a conditioning limit of 0 refuses every fit (a shallow bowl's, or a mug's whose handle dominates)
    tracker = render_tracker(*scene[:2], max_axis_conditioning=0.0)
    assert _snap_body_axis(tracker, build_model(tracker, dict(truth), tracker.config.max_global_frames, [ids[0]])) is None
