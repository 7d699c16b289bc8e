"""The app on a real viser server, driven through its GUI handles' callbacks (no browser)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import viser
from scipy.spatial.transform import Rotation
from test_app_fixtures import served_app, TRUE_EXTENTS, make_sequence

from annotate.app import App
from annotate.app_frames import load_display_frame
from annotate.app_scene import wxyz
from annotate.app_tracking import tracking_engine
from annotate.app_views import AXIS_COLORS, STATUS_COLORS, draw_box, edge_axes, timeline_image
from evaluate.geometry import BOX_EDGES
from sequences.annotation import load_annotation
from sequences.camera import Camera
from sequences.reader import open_sequence


@pytest.fixture(scope="module")
def sequence_root(tmp_path_factory):
    root, poses = make_sequence(tmp_path_factory.mktemp("ui") / "box_seq", frames=4)
    return root, poses


@pytest.fixture
def app(sequence_root, tmp_path):
    with served_app(sequence_root[0], tmp_path) as app:
        yield app


def test_next_frame_button_shows_the_next_frame_at_full_precision(app):
    app.next_button.value = True  # what a click does: run the button's callbacks
    assert app.state.frame == 1
    assert app.frame_slider.value == 2  # the page counts frames from 1
    cloud = app.scene.cloud
    shown = np.asarray(cloud.points, dtype=np.float64) + np.asarray(cloud.position)
    truth = load_display_frame(app.sequence, 1, stride=app.cache.stride)
    # float32 positions relative to a nearby origin: far below a millimetre of error
    assert cloud.precision == "float32"
    assert np.max(np.abs(shown - truth.points.astype(np.float64))) < 1e-6
    np.testing.assert_array_equal(np.asarray(cloud.colors), truth.colors)
    app.prev_button.value = True
    assert app.state.frame == 0
    app.frame_slider.value = 4
    assert app.state.frame == 3 and "frame 4/4" in app.title.content


def test_extents_inputs_flip_and_undo_redo_are_saved(app):
    path = app.state.path
    app.editing.extent_inputs[0].value = 50.0  # mm
    assert path.exists()
    np.testing.assert_allclose(load_annotation(path).extents, [0.05, 0.1, 0.1])
    pose, own = app.state.pose()
    assert not own  # extents are the document's; the frame still has no pose of its own
    app.moving.flip180.value = "y"
    doc = load_annotation(path)
    R0 = Rotation.from_quat(pose.orientation).as_matrix()
    R1 = doc.frames["0000001"].matrix[:3, :3]
    np.testing.assert_allclose(R1[:, 1], R0[:, 1], atol=1e-9)
    np.testing.assert_allclose(R1[:, 0], -R0[:, 0], atol=1e-9)
    app.editing.undo.value = True
    assert "0000001" not in load_annotation(path).frames
    app.editing.undo.value = True
    np.testing.assert_allclose(load_annotation(path).extents, [0.1, 0.1, 0.1])
    assert app.editing.extent_inputs[0].value == 100.0  # the panel follows the document
    app.editing.redo.value = True
    app.editing.redo.value = True
    assert "0000001" in load_annotation(path).frames


def test_gizmo_drag_and_face_drag_edit_the_box(app):
    position = np.array([0.02, -0.01, 0.75])
    orientation = Rotation.from_euler("xyz", [170, 10, 5], degrees=True).as_quat()
    # the end of a gizmo drag commits its pose (one undo step)
    app.editing._on_gizmo(SimpleNamespace(phase="update", target=SimpleNamespace(position=position * 2, wxyz=wxyz(orientation))))
    assert app.state.saves == 0  # intermediate drag updates are not edits
    app.editing._on_gizmo(SimpleNamespace(phase="end", target=SimpleNamespace(position=position, wxyz=wxyz(orientation))))
    doc = load_annotation(app.state.path)
    np.testing.assert_allclose(doc.frames["0000001"].position, position)
    np.testing.assert_allclose(abs(np.dot(doc.frames["0000001"].orientation, orientation)), 1.0, atol=1e-12)
    # the +x face handle dragged 2 cm outwards: width grows by 2 cm, centre moves 1 cm along box x
    handle_end = np.array([0.05 + 0.02, 0.0, 0.0])
    app.editing._on_face(SimpleNamespace(phase="end", target=SimpleNamespace(position=handle_end)), 0, 1)
    doc = load_annotation(app.state.path)
    np.testing.assert_allclose(doc.extents, [0.12, 0.1, 0.1], atol=1e-12)
    R = Rotation.from_quat(orientation).as_matrix()
    np.testing.assert_allclose(doc.frames["0000001"].position, position + 0.01 * R[:, 0], atol=1e-12)
    # the face handles are put back on the faces of the new box
    np.testing.assert_allclose(app.scene.face_handles["x+"].position, [0.06, 0, 0])
    np.testing.assert_allclose(app.scene.face_handles["x-"].position, [-0.06, 0, 0])


def test_fit_box_to_points_finds_the_visible_box(app, sequence_root):
    _, poses = sequence_root
    position, orientation = poses[0]
    # start from the true orientation, a box 2 cm too big and 1 cm off
    app.commit_box(position + [0.01, 0.0, 0.0], orientation, extents=TRUE_EXTENTS + 0.02)
    app.editing.fit.value = True
    doc = load_annotation(app.state.path)
    R = Rotation.from_quat(orientation).as_matrix()
    fitted = doc.frames["0000001"]
    # only the faces seen by the camera are sampled: along each axis the fit is no larger than the truth
    assert np.all(doc.extents <= TRUE_EXTENTS + 0.004)
    # the box is rotated so that two faces show: at least the up-facing side and one side reach the truth
    offset = R.T @ (fitted.position - position)
    assert np.all(np.abs(offset) + doc.extents / 2 <= TRUE_EXTENTS / 2 + 0.004)


def test_category_and_symmetry_choice(app):
    app.editing.category.value = "bottle"
    doc = load_annotation(app.state.path)
    assert doc.category == "bottle" and doc.symmetry == "y"
    app.editing.symmetry.value = "none"
    assert load_annotation(app.state.path).symmetry == "none"
    app.editing.upright.value = True  # not symmetric now: refused with a message, nothing saved
    assert "symmetric" in app.message.content
    assert app.state.saves == 2


def test_accept_reject_and_next_flagged(app):
    ids = app.sequence.ids

    def change(doc):
        from sequences.annotation import FramePose

        for k, frame_id in enumerate(ids):
            doc.frames[frame_id] = FramePose(np.array([0, 0, 0.7]), np.array([1.0, 0, 0, 0]), "tracked", {"flagged": k in (1, 3), "flag_reason": "test"})

    app.state.edit(change)
    app.review.next_flagged.value = True
    assert app.state.frame == 1
    app.review.accept.value = True
    doc = load_annotation(app.state.path)
    assert doc.frames[ids[1]].extra.get("reviewed") == "accepted" and not doc.frames[ids[1]].extra.get("flagged")
    app.review.next_flagged.value = True
    assert app.state.frame == 3
    app.review.reject.value = True
    assert ids[3] not in load_annotation(app.state.path).frames
    app.review.next_flagged.value = True
    assert app.state.frame == 3 and "No flagged" in app.message.content


@pytest.mark.skipif(tracking_engine() is None, reason="tracking engine (annotate.tracking) not installed")
def test_refine_button_moves_a_perturbed_box_towards_the_truth(app, sequence_root):
    _, poses = sequence_root
    position, orientation = poses[0]
    app.state.set_extents(TRUE_EXTENTS)
    ids = app.sequence.ids

    def truth_elsewhere(doc):
        from sequences.annotation import FramePose

        for frame_id, (p, q) in zip(ids[1:], poses[1:]):
            doc.frames[frame_id] = FramePose(np.asarray(p), np.asarray(q), "manual")

    app.state.edit(truth_elsewhere)  # the model of the other frames is right
    start = position + np.array([0.004, -0.003, 0.003])
    app.commit_box(start, orientation)
    app.tracking.refine.value = True
    doc = load_annotation(app.state.path)
    refined = doc.frames["0000001"]
    assert refined.source == "refined"
    assert np.linalg.norm(refined.position - position) < np.linalg.norm(start - position)


def test_box_overlay_and_timeline_images():
    camera = Camera()
    image = np.zeros((480, 640, 3), dtype=np.uint8)
    position = np.array([0.0, 0.0, 1.0])
    orientation = np.array([0.0, 0.0, 0.0, 1.0])
    drawn = draw_box(image, camera, position, orientation, [0.2, 0.2, 0.2], width=3)
    # the middle of the front (-z, nearer) top edge along x lies at v = 239.5 - 525 * 0.1 / 0.9
    corners = np.array([[-0.1, -0.1, 0.9], [0.1, -0.1, 0.9]])
    uv, _ = camera.project(corners)
    u, v = np.round(uv.mean(axis=0)).astype(int)
    assert tuple(drawn[v, u]) == tuple(AXIS_COLORS[0])
    assert v == round(239.5 - 525 * 0.1 / 0.9)
    assert drawn[5, 5].sum() == 0  # far from the box nothing is drawn
    assert sorted(np.bincount(edge_axes())) == [4, 4, 4] and len(BOX_EDGES) == 12
    strip = timeline_image(["manual", "tracked", "flagged", "none"], current=2, width=400, height=20)
    assert strip.shape == (20, 400, 3)
    for k, status in enumerate(["manual", "tracked", "flagged", "none"]):
        assert tuple(strip[10, k * 100 + 50]) == STATUS_COLORS[status]
    assert tuple(strip[0, 250]) == (255, 255, 255) and tuple(strip[0, 50]) == STATUS_COLORS["manual"]


def test_look_through_camera_toggles_the_sensor_view(app):
    app.look_button.value = True
    assert app.look_through and not app.scene.frustum.visible
    assert "through the camera" in app.message.content
    app.look_button.value = True
    assert not app.look_through
    app.frustum_box.value = True
    assert app.scene.frustum.visible


def test_unreadable_sequences_are_refused_with_one_line(tmp_path, capsys):
    from annotate.cli import main
    from sequences.errors import run_cli

    with pytest.raises(SystemExit) as exit_info:
        run_cli(main, [str(tmp_path / "missing")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "missing" in err and "\n" not in err
    # a corrupt first frame is refused before anything is served
    root, _ = make_sequence(tmp_path / "corrupt", frames=1)
    depth = next((root / "depth").iterdir())
    depth.write_bytes(b"not a png")
    with pytest.raises(SystemExit) as exit_info:
        run_cli(main, [str(root), "--port", "0"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert depth.name in err and "corrupt" in err and "\n" not in err


@pytest.mark.skipif(tracking_engine() is None, reason="tracking engine (annotate.tracking) not installed")
def test_track_all_in_the_background_fills_every_frame(app, sequence_root):
    _, poses = sequence_root
    ids = app.sequence.ids
    app.state.set_extents(TRUE_EXTENTS)
    app.commit_box(*poses[0])
    app.state.set_frame(3)
    app.commit_box(*poses[3])
    assert app.tracking.start_tracking(0, len(ids) - 1, wait=True)
    assert app.tracking.progress.value == 100.0
    doc = load_annotation(app.state.path)
    assert set(doc.frames) == set(ids)
    assert [doc.frames[f].source for f in ids] == ["manual", "tracked", "tracked", "manual"]
    for k in (1, 2):  # the engine's contract: a tracked frame lands near the truth, or it is flagged for review
        pose = doc.frames[ids[k]]
        assert np.linalg.norm(pose.position - poses[k][0]) < 0.01 or pose.extra.get("flagged")
    flagged = sum(bool(doc.frames[f].extra.get("flagged")) for f in ids)
    assert "Tracked 4 frames" in app.message.content and f"{flagged} flagged" in app.message.content
    if flagged:
        app.review.next_flagged.value = True
        assert app.state.status() == "flagged"
    app.editing.undo.value = True  # the whole run is one undo step
    assert set(load_annotation(app.state.path).frames) == {ids[0], ids[3]}


@pytest.mark.skipif(tracking_engine() is None, reason="tracking engine (annotate.tracking) not installed")
def test_snap_upright_puts_the_box_axis_on_a_cylinder_axis(tmp_path):
    extents = np.array([0.08, 0.14, 0.08])
    root, poses = make_sequence(tmp_path / "can_seq", frames=3, shape="cylinder", extents=extents)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = App(server, open_sequence(root))
    try:
        app.editing.category.value = "can"
        assert app.state.annotation.symmetry == "y"
        app.state.set_extents(extents)
        position, orientation = poses[0]
        true_axis = Rotation.from_quat(orientation).as_matrix()[:, 1]
        tilted = (Rotation.from_quat(orientation) * Rotation.from_euler("zx", [7, -5], degrees=True)).as_quat()
        app.commit_box(position, tilted)
        app.editing.upright.value = True
        snapped = load_annotation(app.state.path).frames["0000001"]
        axis = snapped.matrix[:3, 1]
        before = np.degrees(np.arccos(np.clip(Rotation.from_quat(tilted).as_matrix()[:, 1] @ true_axis, -1, 1)))
        after = np.degrees(np.arccos(np.clip(axis @ true_axis, -1, 1)))
        assert before > 8.0 and after < 2.0, (before, after)
        # the free turn about the axis is the canonical one: object +z towards the camera
        z = snapped.matrix[:3, 2]
        to_camera = -snapped.position - np.dot(-snapped.position, axis) * axis
        assert np.dot(z, to_camera / np.linalg.norm(to_camera)) > 0.999
    finally:
        app.close()
        server.stop()


def test_timeline_never_hides_a_flagged_frame():
    statuses = ["tracked"] * 2000
    statuses[1234] = "flagged"
    statuses[5] = "none"
    strip = timeline_image(statuses, current=0, width=600, height=20)
    row = strip[10]
    flagged_columns = np.flatnonzero(np.all(row == STATUS_COLORS["flagged"], axis=1))
    assert flagged_columns.tolist() == [1234 * 600 // 2000]
    assert np.all(row[1] == STATUS_COLORS["none"])
    # everything else is tracked (an independent per-column loop gives the same strip)
    order = ["manual", "refined", "tracked", "none", "flagged"]
    for c in range(600):
        frames = range(c * 2000 // 600, max((c + 1) * 2000 // 600, c * 2000 // 600 + 1))  # [first, next first)
        worst = max((statuses[f] for f in frames), key=order.index)
        assert tuple(row[c]) == STATUS_COLORS[worst]


@pytest.mark.parametrize("n", [3, 599, 600, 601, 1999])
def test_timeline_columns_match_a_per_column_loop(n):
    rng = np.random.default_rng(n)
    order = ["manual", "refined", "tracked", "none", "flagged"]
    statuses = [order[i] for i in rng.choice(5, size=n, p=[0.3, 0.2, 0.4, 0.08, 0.02])]
    row = timeline_image(statuses, current=n - 1, width=600, height=20)[10]
    for c in range(600):
        lo = min(c * n // 600, n - 1)
        hi = max(min((c + 1) * n // 600, n), lo + 1)
        worst = max(statuses[lo:hi], key=order.index)
        assert tuple(row[c]) == STATUS_COLORS[worst], c


@pytest.mark.parametrize("depth_m", [0.4, 3.0])
def test_the_tool_opens_sequences_near_and_far(tmp_path, depth_m):
    """Every control's range follows the data: a sequence 3 m away (points a centimetre apart) opens, as one at 0.4 m."""
    from PIL import Image

    from sequences.reader import open_sequence

    root = tmp_path / f"far_{depth_m}"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for k in range(2):
        Image.fromarray(np.full((480, 640, 3), 120, np.uint8)).save(root / "rgb" / f"{k + 1:07d}.png")
        Image.fromarray(np.full((480, 640), int(depth_m * 1000), np.uint16)).save(root / "depth" / f"{k + 1:07d}.png")
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        app = App(server, open_sequence(root))
        slider = app.point_slider
        assert slider.min <= slider.value <= slider.max
        app.close()
    finally:
        server.stop()


def test_websocket_handshakes_from_other_origins_are_refused():
    """A page elsewhere cannot drive the tool: its Origin is refused; the tool's own page and scripts are let in."""
    import websockets.exceptions
    import websockets.sync.client

    from annotate.origin_guard import guard_origins

    guard_origins()
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        port = server.get_port()
        url = f"ws://127.0.0.1:{port}"
        for origin in (f"http://127.0.0.1:{port}", f"http://localhost:{port}", None):
            with websockets.sync.client.connect(url, origin=origin, subprotocols=["viser-v1"], open_timeout=5) as connection:
                assert connection.protocol is not None
        with pytest.raises(websockets.exceptions.InvalidStatus) as refused:
            websockets.sync.client.connect(url, origin="http://evil.example", subprotocols=["viser-v1"], open_timeout=5)
        assert refused.value.response.status_code == 403
    finally:
        server.stop()
