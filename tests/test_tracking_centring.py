"""A hinged object's centre along its hinge from the ends its frames see (annotate/tracking/centring.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_tracking_render import object_offset, posed_off

from annotate.tracking.centring import Span, centre_offsets, centred, end_faces, extent_along
from annotate.tracking.engine import _centred_on_hinge
from annotate.tracking.refine import build_model, min_hits_for


#: the rendered laptop's hinge, in its object frame
X = np.array([1.0, 0.0, 0.0])


def _spans_along_x(tracker, ids: list[str], poses: dict[str, np.ndarray], model_poses: dict[str, np.ndarray] | None = None) -> list:
    """Each frame's :class:`Span` along the hinge at ``poses``, against the model of ``model_poses`` (all of ``poses``
    where None)."""
    model = build_model(tracker, poses if model_poses is None else model_poses, len(ids), [ids[0]])
    target = model.target(min_hits_for(model, tracker.config))
    return [extent_along(tracker, f, poses[f], target, X) for f in ids]


def test_offsets_are_the_median_middle_of_the_frames_that_saw_both_ends():
    # 0.30 m wide; frames 3 and 4 see one end only (the hand): shorter spans, middles pulled to the seen side
    spans = [(0.300, 0.010), (0.301, 0.012), (0.299, 0.011), (0.250, -0.020), (0.260, -0.030), (0.300, 0.009), None, (0.300, -0.004), (0.298, -0.006)]
    offsets = centre_offsets(spans, tolerance=0.005, window=1)
    # frame 3 has frames 2-4 about it, of which frame 2 alone saw both ends; frame 6 has no span of its own and takes
    # the median of frames 5 and 7
    expected = [0.011, 0.011, 0.0115, 0.011, 0.009, 0.009, 0.0025, -0.005, -0.005]
    assert np.allclose(offsets, expected, atol=1e-12)
    # no frame saw both ends within the window: the offset of the stretch it lies in, interpolated between the
    # nearest frames that have one (frames 2 and 3 between frames 1 and 4), held past the last one
    short = (0.20, 0.05)
    offsets = centre_offsets([(0.30, 0.01), short, short, short, short, (0.30, 0.03)], 0.005, 1)
    assert np.allclose(offsets, [0.01, 0.01, 0.01 + 0.02 / 3, 0.01 + 0.04 / 3, 0.03, 0.03], atol=1e-15)
    assert np.array_equal(centre_offsets([(0.30, 0.01), short, short, short], 0.005, 1), [0.01, 0.01, 0.01, 0.01])
    assert np.array_equal(centre_offsets([None, None, (0.30, 0.01), None, None], 0.005, 1), [0.01] * 5)
    # no span at all: every frame left where it is
    assert np.array_equal(centre_offsets([None, None], 0.005, 2), [0.0, 0.0])


def test_a_frame_whose_box_slid_takes_the_middle_its_uncut_end_gives():
    # a 0.30 m object; frames 0-2 and 4-6 saw both ends, about 2 mm from the box centre. Frame 3's box slid 45 mm
    # along the axis: the object's centre lies at -45 mm in it, its ends at -195 and +105 mm, and the crop (+-172
    # mm) cuts the low one, which the model stops short of (-155 mm): the span's middle (-25 mm) is no measure, and
    # the frames about it share none of its offset
    full = [Span(0.300, 0.002, -0.148, 0.152), Span(0.301, 0.0025, -0.148, 0.153), Span(0.299, 0.0015, -0.148, 0.151)]
    slid = Span(0.260, -0.025, -0.155, 0.105, cut_low=True)
    offsets = centre_offsets(full + [slid] + full, 0.005, 1)
    # its high end, half the width of the frames that saw both ends (0.300 m) in: -45 mm
    assert offsets[3] == pytest.approx(0.105 - 0.150, abs=1e-12)
    assert np.allclose(offsets[[0, 1, 2, 4, 5, 6]], [0.00225, 0.002, 0.002, 0.00225, 0.002, 0.002], atol=1e-12)
    # an end hidden by the hand, no end cut: the frames about it decide, as before (frames 2 and 4: 1.75 mm)
    hidden = Span(0.260, -0.018, -0.148, 0.112)
    assert centre_offsets(full + [hidden] + full, 0.005, 1)[3] == pytest.approx(0.00175, abs=1e-12)
    # a cut end whose other end agrees with the frames about it within 10 mm: they are the better measure
    near = Span(0.280, 0.002 + 0.008, -0.130, 0.150 + 0.008, cut_low=True)
    assert centre_offsets(full + [near] + full, 0.005, 1)[3] == pytest.approx(0.00175, abs=1e-12)
    # both ends cut (the object longer than the crop): nothing to measure it by
    both = Span(0.260, -0.025, -0.155, 0.105, cut_low=True, cut_high=True)
    assert centre_offsets(full + [both] + full, 0.005, 1)[3] == pytest.approx(0.00175, abs=1e-12)


def test_a_centred_pose_moves_its_box_centre_along_its_own_axis():
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    pose[:3, 3] = [0.1, -0.05, 0.7]
    direction = np.array([1.0, 0.0, 0.0])
    moved = centred(pose, 0.012, direction)
    assert np.array_equal(moved[:3, :3], pose[:3, :3])
    # the new box centre is the old object-frame point 12 mm along x
    assert np.allclose(moved[:3, 3], pose[:3, :3] @ [0.012, 0.0, 0.0] + pose[:3, 3], atol=1e-15)


@pytest.mark.slow
def test_frames_carried_along_the_hinge_are_brought_back_to_the_middle_of_its_ends(rendered_laptop):
    _, mesh, truth = rendered_laptop
    # every box 12 mm along the hinge: the model of all frames comes out shifted alike
    tracker, ids, poses = posed_off(rendered_laptop, object_offset(translation_m=(0.012, 0.0, 0.0)))
    spans = _spans_along_x(tracker, ids, poses)
    assert all(s is not None for s in spans)
    width = mesh.extents[0]
    offsets = centre_offsets(spans, 0.005, 2)
    left = [abs(np.linalg.inv(truth[f]) @ centred(poses[f], o, X))[0, 3] for f, o in zip(ids, offsets)]
    # measured: spans 1.4-2.3 mm short of the laptop's width (the end percentiles), the centres 0.90-0.93 mm from the
    # truth (12 mm before; each frame sees the +x end face, and lies half the spans' shortfall off)
    assert all(abs(s[0] - width) < 0.005 for s in spans), [s[0] for s in spans]
    assert max(left) < 0.0015, left


@pytest.mark.slow
def test_a_frame_slid_past_the_crop_along_the_hinge_is_brought_back(rendered_laptop):
    _, mesh, truth = rendered_laptop
    tracker, ids, poses = posed_off(rendered_laptop, np.eye(4))
    # one frame's box 45 mm along the hinge, past the crop's slack (8 % of the width and 1 cm): the model of the other
    # frames stops at the laptop's end, 45 mm short of where that frame's points run on to the crop
    slid = ids[5]
    poses[slid] = poses[slid] @ object_offset(translation_m=(0.045, 0.0, 0.0))
    spans = _spans_along_x(tracker, ids, poses, {f: p for f, p in poses.items() if f != slid})
    assert spans[5].cut_low and not spans[5].cut_high
    assert not any(s.cut_low or s.cut_high for i, s in enumerate(spans) if i != 5)
    offsets = centre_offsets(spans, 0.005, 1)
    left = [(np.linalg.inv(truth[f]) @ centred(poses[f], o, X))[0, 3] for f, o in zip(ids, offsets)]
    # measured: the slid frame's span 317.9 mm of the laptop's 355.4 (the others 353.1-354.0), its middle 26 mm off;
    # moved by its high end, it lies 1.09 mm from the truth (46.1 mm taking the frames about it, as before the rule);
    # the others 0.95-1.11 mm, as before
    assert abs(left[5]) < 0.002 and max(abs(v) for v in left) < 0.002, left


@pytest.mark.slow
def test_the_engine_centres_along_the_snapped_hinge_before_the_snap(rendered_laptop):
    truth = rendered_laptop[2]
    tilt = object_offset(rotvec_deg=(0.0, 4.0, 4.0))
    # the boxes slid along the hinge, then turned off it
    tracker, ids, poses = posed_off(rendered_laptop, object_offset(translation_m=(0.015, 0.0, 0.0)) @ tilt)
    snap = np.linalg.inv(tilt)  # the hinge snap that turns them back (engine: poses @ snap, after the centring)
    model = build_model(tracker, poses, len(ids), [ids[0]])
    out = _centred_on_hinge(tracker, ids, poses, snap, model)
    left = np.array([(np.linalg.inv(truth[f]) @ out[f] @ snap)[:3, 3] for f in ids])
    # measured: 1.0-1.1 mm along x (as above), 0 along y and z; along the unsnapped x it would be 19 mm off
    assert np.abs(left[:, 0]).max() < 0.0015 and np.abs(left[:, 1:]).max() < 1e-4, left


def test_a_frame_that_sees_an_end_face_takes_the_middle_that_face_gives():
    # a 0.300 m object; frames 0-2 and 4-6 saw both ends (spans 2 mm short of the width: their outlines), about 2 mm
    # from the box centre. Frame 3 sees its high end's face at +0.156 m: the object's centre lies 6 mm along the axis
    # there, whatever the frames about it say
    full = [Span(0.298, 0.002, -0.147, 0.151), Span(0.299, 0.0025, -0.147, 0.152), Span(0.297, 0.0015, -0.147, 0.150)]
    faced = Span(0.300, 0.002, -0.148, 0.152, face_high=0.156)
    offsets = centre_offsets(full + [faced] + full, 0.005, 1)
    # half the median width of the frames that saw both ends (0.298 m) in from the face
    assert offsets[3] == pytest.approx(0.156 - 0.149, abs=1e-12)
    # its neighbours keep the median middle of the frames about them (frame 3's own span counts there)
    assert np.allclose(offsets[[2, 4]], [0.002, 0.002], atol=1e-12)
    # both faces seen: the mean of the two middles
    both = Span(0.300, 0.002, -0.148, 0.152, face_low=-0.145, face_high=0.156)
    assert centre_offsets(full + [both] + full, 0.005, 1)[3] == pytest.approx(((-0.145 + 0.149) + (0.156 - 0.149)) / 2, abs=1e-12)
    # a face seen at a slid frame's uncut end decides over the cut rule's middle (the same end, measured on its face)
    slid = Span(0.260, -0.025, -0.155, 0.105, cut_low=True, face_high=0.1065)
    assert centre_offsets(full + [slid] + full, 0.005, 1)[3] == pytest.approx(0.1065 - 0.149, abs=1e-12)


@pytest.mark.slow
def test_an_end_face_seen_gives_the_end_where_the_span_falls_short(rendered_laptop):
    _, mesh, truth = rendered_laptop
    # every box 12 mm along the hinge; the rendered frames see the laptop's high side (its +x end face), not its low one
    tracker, ids, poses = posed_off(rendered_laptop, object_offset(translation_m=(0.012, 0.0, 0.0)))
    spans = _spans_along_x(tracker, ids, poses)
    width = mesh.extents[0]
    # the true ends in the boxes' frame: the object's centre lies 12 mm below the box centre
    low, high = -width / 2 - 0.012, width / 2 - 0.012
    face = np.array([s.face_high for s in spans])
    assert all(np.isnan(s.face_low) for s in spans)
    # measured: the faces within 0.02 mm of the end; the spans' high ends 0.10-0.16 mm beyond it, their low ends (the
    # outline) 1.5-2.5 mm short
    assert np.abs(face - high).max() < 1e-4, (face - high) * 1000
    assert min(s.low - low for s in spans) > 0.001
    # the end face from its frames' own points, with or without the end under a frame's span end: the same
    assert end_faces(tracker, ids[0], poses[ids[0]], X, spans[0].low, spans[0].high)[1] == spans[0].face_high
