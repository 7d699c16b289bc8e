"""The sequence reader: pairing, camera.yaml, lazy loading, back-projection and bad inputs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from sequences import Camera, InputError, frame_points, open_sequence, pair_frames
from sequences.pointcloud import in_oriented_box

from seqfactory import redwood_sequence, write_frame

REPO = Path(__file__).resolve().parents[1]


def test_pairs_by_nearest_timestamp_when_numbering_differs(tmp_path):
    seq = open_sequence(redwood_sequence(tmp_path / "s", n=5))
    assert len(seq) == 5
    # REDWOOD75's case: rgb 0000210 goes with depth 0000211
    assert seq.frames[0].id == "0000210"
    assert seq.frames[0].depth_path.name.startswith("0000211-")
    assert all(f.depth_time_us - f.color_time_us == 2_500 for f in seq.frames)
    assert seq.ids == [f"{210 + i:07d}" for i in range(5)]


def test_pairing_reports_unpaired_and_uses_each_depth_once(tmp_path):
    def p(name):
        return Path(name)
    color = [p("0000001-000000000000.jpg"), p("0000002-000000033000.jpg"), p("0000003-000000066000.jpg"), p("0000004-000000500000.jpg")]
    # depth 2 sits between colour 1 and 2 but nearer colour 2; colour 4 has no depth within tolerance
    depth = [p("0000001-000000001000.png"), p("0000002-000000030000.png"), p("0000003-000000067000.png"), p("0000009-000000900000.png")]
    pairing = pair_frames(color, depth, tolerance_us=16_667)
    assert [(f.color_path.name[:7], f.depth_path.name[:7]) for f in pairing.frames] == [("0000001", "0000001"), ("0000002", "0000002"), ("0000003", "0000003")]
    assert [c.name[:7] for c in pairing.unpaired_color] == ["0000004"]
    assert [d.name[:7] for d in pairing.unpaired_depth] == ["0000009"]
    # two colour frames nearest to one depth frame: the closer one wins, the other is unpaired
    pairing = pair_frames([p("0000001-000000000000.jpg"), p("0000002-000000010000.jpg")], [p("0000001-000000008000.png")], 16_667)
    assert [f.id for f in pairing.frames] == ["0000002"]
    assert [c.name[:7] for c in pairing.unpaired_color] == ["0000001"]


def test_sorted_order_pairing_without_timestamps_and_png_colour(tmp_path):
    root = tmp_path / "plain"
    for i in range(3):
        write_frame(root, f"frame{i:03d}.png", f"d{i:03d}.png", seed=i)
    seq = open_sequence(root)
    assert seq.ids == ["frame000", "frame001", "frame002"]
    assert seq.color("frame001").shape == (480, 640, 3)
    assert seq.color(1).dtype == np.uint8


def test_camera_yaml_overrides_intrinsics_and_depth_scale(tmp_path):
    root = redwood_sequence(tmp_path / "s", n=2, size=(320, 240))
    (root / "camera.yaml").write_text("fx: 300.0\nfy: 301.0\ncx: 159.5\ncy: 119.5\nwidth: 320\nheight: 240\ndepth_scale: 0.0001\n")
    seq = open_sequence(root)
    assert seq.camera == Camera(300.0, 301.0, 159.5, 119.5, 320, 240, 0.0001)
    # raw value 600 at depth_scale 1e-4 is 6 cm
    assert np.isclose(seq.depth(0).max(), 0.06)


def test_default_camera_is_primesense(tmp_path):
    seq = open_sequence(redwood_sequence(tmp_path / "s", n=1))
    assert seq.camera == Camera(525.0, 525.0, 319.5, 239.5, 640, 480, 0.001)
    assert np.allclose(seq.camera.K, [[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]])


def test_opening_reads_no_images(tmp_path, monkeypatch):
    root = redwood_sequence(tmp_path / "s", n=3)
    import sequences.images as images

    def forbidden(*args, **kwargs):
        raise AssertionError("an image was read while opening")

    monkeypatch.setattr(images, "open_image", forbidden)
    seq = open_sequence(root)
    assert len(seq) == 3


def test_backprojection_inverts_projection_at_pixel_centres():
    cam = Camera()
    depth = np.zeros((480, 640), np.float32)
    depth[100, 200] = 1.5
    depth[479, 639] = 0.7
    points, index = cam.backproject(depth)
    assert index.tolist() == [100 * 640 + 200, 479 * 640 + 639]
    uv, z = cam.project(points)
    assert np.allclose(uv, [[200, 100], [639, 479]], atol=1e-9)
    assert np.allclose(z, [1.5, 0.7], atol=1e-6)
    # the principal point's pixel lies half a pixel off the optical axis: x = (320 - 319.5) / 525 * z
    depth2 = np.zeros((480, 640), np.float32)
    depth2[240, 320] = 2.0
    p, _ = cam.backproject(depth2)
    assert np.allclose(p, [[0.5 / 525 * 2.0, 0.5 / 525 * 2.0, 2.0]], atol=1e-6)


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_a_window_backprojects_the_same_points_less_those_outside(stride):
    cam = Camera()
    rng = np.random.default_rng(4)
    depth = np.where(rng.random((480, 640)) < 0.7, rng.uniform(0.4, 2.0, (480, 640)), 0.0).astype(np.float32)
    mask = rng.random((480, 640)) < 0.8
    corners = np.array([[-0.0935, -0.05, 0.8], [0.12, 0.07, 0.9], [0.0, 0.0, 1.2]])  # camera frame
    rows, cols = cam.window(corners)
    assert rows.start % 6 and cols.start % 6  # starts off every stride's grid: the first row and column are rounded up
    uv, _ = cam.project(corners)
    assert cols.start <= np.floor(uv[:, 0].min()) - 1 and cols.stop >= np.ceil(uv[:, 0].max()) + 2
    assert rows.start <= np.floor(uv[:, 1].min()) - 1 and rows.stop >= np.ceil(uv[:, 1].max()) + 2
    points, index = cam.backproject(depth, mask, stride=stride, window=(rows, cols))
    full, full_index = cam.backproject(depth, mask, stride=stride)
    v, u = np.divmod(full_index, 640)
    inside = (v >= rows.start) & (v < rows.stop) & (u >= cols.start) & (u < cols.stop)
    assert np.array_equal(index, full_index[inside]) and np.array_equal(points, full[inside])
    # a window clipped at the image's border holds the border's pixels
    edge = cam.window(np.array([[0.2, 0.1, 0.6], [0.9, 0.5, 0.7]]))
    assert edge[0].stop == 480 and edge[1].stop == 640
    points, index = cam.backproject(depth, stride=stride, window=edge)
    clipped = cam.backproject(depth, stride=stride)[1]
    cv, cu = np.divmod(clipped, 640)
    assert np.array_equal(index, clipped[(cv >= edge[0].start) & (cu >= edge[1].start)])
    # a point behind the camera bounds nothing: the whole image
    assert cam.window(np.array([[0.0, 0.0, 1.0], [0.1, 0.0, -0.2]])) == (slice(0, 480), slice(0, 640))


def test_frame_points_masked_and_box_cropped(tmp_path):
    root = redwood_sequence(tmp_path / "s", n=1)
    seq = open_sequence(root)
    full = frame_points(seq, 0)
    assert len(full) == 480 * 640 * 3 // 4  # the top quarter has no depth
    mask = np.zeros((480, 640), bool)
    mask[200:210, 300:320] = True
    masked = frame_points(seq, 0, mask=mask)
    assert len(masked) == 200
    assert np.allclose(masked.points[:, 2], 0.6)
    # colours come from the same pixels
    assert np.array_equal(masked.colors, seq.color(0).reshape(-1, 3)[masked.pixels])
    # a box 4 cm wide around the optical axis at 0.6 m, rotated 30 degrees about z
    q = Rotation.from_euler("z", 30, degrees=True).as_quat()
    boxed = frame_points(seq, 0, box=([0, 0, 0.6], q, [0.04, 0.04, 0.01]))
    assert len(boxed) > 0
    local = (boxed.points - [0, 0, 0.6]) @ Rotation.from_quat(q).as_matrix()
    assert np.all(np.abs(local[:, :2]) <= 0.02 + 1e-12)
    # pixel area check: a 4 cm square at 0.6 m covers (0.04 * 525 / 0.6)^2 = 1225 pixels
    assert abs(len(boxed) - 1225) < 80
    assert in_oriented_box(np.array([[0, 0, 0.6]]), [0, 0, 0.6], q, [0.01, 0.01, 0.01]).all()


def _run(*args):
    return subprocess.run([sys.executable, "-m", "sequences", *map(str, args)], capture_output=True, text=True, cwd=REPO)


def _assert_one_line_error(result, *fragments):
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_cli_summary(tmp_path):
    result = _run(redwood_sequence(tmp_path / "s", n=3), "--check")
    assert result.returncode == 0, result.stderr
    assert "3 frames" in result.stdout


def test_bad_input_missing_folders(tmp_path):
    root = tmp_path / "s"
    root.mkdir()
    _assert_one_line_error(_run(root), str(root / "rgb"), "missing rgb/")
    (root / "rgb").mkdir()
    _assert_one_line_error(_run(root), str(root / "depth"), "missing depth/")
    _assert_one_line_error(_run(tmp_path / "nope"), "does not exist")


def test_bad_input_zero_frames(tmp_path):
    root = tmp_path / "s"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    _assert_one_line_error(_run(root), "no colour images")


def test_bad_input_corrupt_image(tmp_path):
    root = redwood_sequence(tmp_path / "s", n=2)
    bad = sorted((root / "rgb").iterdir())[1]
    bad.write_bytes(b"\xff\xd8\xff\xe0 this is not a jpeg")
    _assert_one_line_error(_run(root, "--check"), str(bad), "corrupt")


def test_bad_input_truncated_depth(tmp_path):
    root = redwood_sequence(tmp_path / "s", n=1)
    bad = next((root / "depth").iterdir())
    bad.write_bytes(bad.read_bytes()[:200])
    _assert_one_line_error(_run(root, "--check"), str(bad))


def test_bad_input_depth_not_16_bit(tmp_path):
    root = redwood_sequence(tmp_path / "s", n=1)
    bad = next((root / "depth").iterdir())
    Image.fromarray(np.full((480, 640), 90, np.uint8)).save(bad)
    _assert_one_line_error(_run(root, "--check"), str(bad), "not 16-bit")


def test_bad_input_sizes_differ(tmp_path):
    root = redwood_sequence(tmp_path / "s", n=1)
    bad = next((root / "depth").iterdir())
    Image.fromarray(np.full((240, 320), 900, np.uint16)).save(bad)
    _assert_one_line_error(_run(root, "--check"), str(bad), "320x240")


def test_bad_input_depth_without_valid_pixel(tmp_path):
    root = redwood_sequence(tmp_path / "s", n=1)
    bad = next((root / "depth").iterdir())
    Image.fromarray(np.zeros((480, 640), np.uint16)).save(bad)
    _assert_one_line_error(_run(root, "--check"), str(bad), "no valid pixel")


@pytest.mark.parametrize("text, fragment", [
    ("depth_scale: 1.0\n", "implausible"),
    ("fx: -3\n", "fx must be a positive"),
    ("fx: [1, 2\n", "malformed YAML"),
    ("focal: 500\n", "unknown camera keys"),
    ("width: 640.5\n", "width must be an integer"),
])
def test_bad_camera_yaml(tmp_path, text, fragment):
    root = redwood_sequence(tmp_path / "s", n=1)
    (root / "camera.yaml").write_text(text)
    _assert_one_line_error(_run(root), str(root / "camera.yaml"), fragment)
    with pytest.raises(InputError):
        open_sequence(root)


def test_decoded_depth_is_kept_read_only_within_its_budget(tmp_path, monkeypatch):
    """`check` decodes every frame; the work's next read of a frame is that image (read-only, so no reader changes
    it for the next), the frames read after DEPTH_CACHE_BYTES is full are read again, and a pickled sequence starts empty."""
    import pickle

    import sequences.reader as reader

    seq = open_sequence(redwood_sequence(tmp_path / "seq", n=4))
    seq.check()
    first = seq.depth_raw(0)
    assert seq.depth_raw(0) is first and not first.flags.writeable
    with pytest.raises(ValueError):
        first[0, 0] = 1
    assert np.array_equal(seq.depth(0), first.astype(np.float32) * np.float32(seq.camera.depth_scale))
    monkeypatch.setattr(reader, "DEPTH_CACHE_BYTES", 2 * first.nbytes)  # room for two frames
    fresh = open_sequence(tmp_path / "seq")
    images = [fresh.depth_raw(i) for i in range(4)]
    assert fresh.depth_raw(0) is images[0] and fresh.depth_raw(1) is images[1]  # the first two, kept for the next pass
    again = fresh.depth_raw(3)
    assert again is not images[3] and np.array_equal(again, images[3])  # read again from its file
    copy = pickle.loads(pickle.dumps(fresh))
    assert not copy._decoded and np.array_equal(copy.depth_raw(1), images[1])
