"""FrameStore crops: the points of a known wall inside a box, and repeated crops (kept ones) as the caller's own arrays;
crops cut from a held wider crop; frames read ahead on threads (preload) as read one by one."""

from __future__ import annotations

import numpy as np

from annotate.tracking.frames import FrameStore
from sequences.camera import Camera


class _WallSequence:
    """A sequence stand-in: every frame sees a flat wall at ``depth`` m, colour = pixel column / 640."""

    def __init__(self, depth: float) -> None:
        self.camera = Camera()
        self.depth_m = depth
        self.reads = 0

    def depth(self, frame_id: str) -> np.ndarray:
        self.reads += 1
        return np.full((self.camera.height, self.camera.width), self.depth_m, np.float32)

    def color(self, frame_id: str) -> np.ndarray:
        u = np.arange(self.camera.width, dtype=np.float64) / self.camera.width * 255
        return np.broadcast_to(u[None, :, None], (self.camera.height, self.camera.width, 3)).astype(np.uint8)


def _box_pose(x: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = [x, 0.0, 1.0]
    return pose


def test_crop_keeps_the_wall_inside_the_box_and_repeats_exactly():
    sequence = _WallSequence(1.0)
    store = FrameStore(sequence, stride=2, colors=True, crop_cache=1)
    extents = np.array([0.2, 0.1, 0.1])  # full sides, m: the wall at z = 1 lies inside the box's z range
    points, colors = store.crop("a", _box_pose(0.05), extents, margin=0.0)
    # independent truth: the stride-2 pixels whose ray meets the wall (z = 1) within x in [-0.05, 0.15], y in [-0.05, 0.05]
    camera = sequence.camera
    u = np.arange(0, camera.width, 2)
    v = np.arange(0, camera.height, 2)
    x = (u - camera.cx) / camera.fx
    y = (v - camera.cy) / camera.fy
    expected = np.count_nonzero((x >= -0.05) & (x <= 0.15)) * np.count_nonzero(np.abs(y) <= 0.05)
    assert len(points) == expected
    assert np.allclose(points[:, 2], 1.0)
    assert points[:, 0].min() >= -0.05 and points[:, 0].max() <= 0.15 and np.abs(points[:, 1]).max() <= 0.05
    column = np.round(points[:, 0] * camera.fx + camera.cx)  # the pixel column each point came from
    assert np.allclose(colors[:, 0], np.floor(column / camera.width * 255) / 255, atol=1e-6)
    # the caller's own arrays: changing them does not change the next crop of the same box
    kept = points.copy()
    points[:] = 0.0
    colors[:] = 0.0
    again, again_colors = store.crop("a", _box_pose(0.05), extents, margin=0.0)
    assert np.array_equal(again, kept) and again_colors.max() > 0
    # another box, then the first again (evicted from a one-crop cache): computed anew, the same points
    other, _ = store.crop("a", _box_pose(-0.05), extents, margin=0.0)
    assert other[:, 0].max() <= 0.05
    assert np.array_equal(store.crop("a", _box_pose(0.05), extents, margin=0.0)[0], kept)
    # voxel-downsampled: one point per 2 cm voxel of the wall (the box spans 10 x 5 voxels at most)
    coarse, coarse_colors = store.crop("a", _box_pose(0.05), extents, margin=0.0, voxel=0.02)
    assert 40 <= len(coarse) <= 66 and coarse_colors.shape == coarse.shape
    # a one-off crop (keep=False): the same points, and the kept one stays kept
    kept_keys = list(store._crops)
    assert np.array_equal(store.crop("a", _box_pose(-0.05), extents, margin=0.0, keep=False)[0], other)
    assert list(store._crops) == kept_keys
    assert sequence.reads == 1  # the frame itself is read once


def test_crop_without_colours_gives_zeros_and_an_empty_box_nothing():
    store = FrameStore(_WallSequence(1.0), stride=2, colors=False)
    points, colors = store.crop("a", _box_pose(0.0), np.array([0.1, 0.1, 0.1]), margin=0.0)
    assert len(points) > 0 and colors.shape == points.shape and not colors.any()
    behind = _box_pose(0.0)
    behind[2, 3] = 2.0  # a box 1 m behind the wall sees nothing of it
    points, colors = store.crop("a", behind, np.array([0.1, 0.1, 0.1]), margin=0.0)
    assert points.shape == (0, 3) and colors.shape == (0, 3)


def test_a_batch_of_crops_equals_the_crops_one_by_one_on_worker_processes():
    """FrameStore.crops: the arrays of crop() for each request, duplicates and kept crops included, computed on two
    processes; the batch's crops are kept, and a crop kept before the batch survives it even where the batch
    pushes it out of the cache."""
    import sys

    extents = np.array([0.2, 0.1, 0.1])
    poses = [_box_pose(0.01 * k) for k in range(20)]
    requests = [(f"f{k}", poses[k]) for k in range(20)] + [("f3", poses[3])]  # a duplicate
    one_by_one = FrameStore(_WallSequence(1.0), stride=2, colors=True)
    expected = [one_by_one.crop(f, pose, extents, 0.0, 0.004) for f, pose in requests]
    store = FrameStore(_WallSequence(1.0), stride=2, colors=True, crop_cache=10)
    early = store.crop("f0", poses[0], extents, 0.0, 0.004)  # kept; the batch's 19 new crops push it out
    workers = 2 if sys.platform.startswith("linux") else 1
    got = store.crops(requests, extents, 0.0, 0.004, workers=workers)
    assert len(got) == len(expected)
    for (p, c), (q, d) in zip(got, expected):
        assert np.array_equal(p, q) and np.array_equal(c, d)
        assert len(p) > 100
    np.testing.assert_array_equal(got[0][0], early[0])
    assert ("f0", poses[0].tobytes()) not in {key[:2] for key in store._crops}  # pushed out, yet served above
    got[19][0][:] = 0  # the caller's own arrays: the kept crop is untouched
    again = store.crop("f19", poses[19], extents, 0.0, 0.004)
    np.testing.assert_array_equal(again[0], expected[19][0])
    assert store.sequence.reads == 20  # every frame read once, here (not on a worker): f0 before the batch, 19 in it


def test_crops_inside_a_held_crop_are_cut_from_it_and_others_from_the_image():
    """FrameStore.hold: a later voxelled crop whose box lies inside the held one is its voxels whose centre lies in the
    box (the wall's 2 cm voxels: whole ones, the means of all their points); a box reaching outside it, a crop at
    another voxel or at full resolution come from the image as without a held crop."""
    from annotate.tracking.frames import HELD_MARGIN_M

    extents, voxel = np.array([0.2, 0.1, 0.1]), 0.02
    sequence = _WallSequence(1.0)
    store = FrameStore(sequence, stride=2, colors=True)
    plain = FrameStore(_WallSequence(1.0), stride=2, colors=True)  # no held crops: the image's crops
    store.hold([("a", _box_pose(0.0)), ("b", _box_pose(0.3))], extents, voxel)
    wide, wide_colors = plain.crop("a", _box_pose(0.0), extents, HELD_MARGIN_M, voxel)  # what "a" holds
    assert np.allclose(wide[:, 2], 1.0)
    image_crop = store._crop
    store._crop = None  # a crop served from the held one touches no image: calling this would raise

    # moved 1 cm, with a 1 cm margin: 2 cm of the held 4 cm used
    points, colors = store.crop("a", _box_pose(0.01), extents, 0.01, voxel)
    inside = (np.abs(wide[:, 0] - 0.01) <= 0.11) & (np.abs(wide[:, 1]) <= 0.06)
    np.testing.assert_array_equal(points, wide[inside])
    np.testing.assert_array_equal(colors, wide_colors[inside])
    # the wall's voxels: 2 cm apart, so the box's 22 x 12 cm hold 11 x 6 of their centres, give or take one per side
    assert 10 * 5 <= len(points) <= 12 * 7
    # a model's batch of crops: the held frames cut, the same arrays as one by one
    batch = store.crops([("a", _box_pose(0.01)), ("b", _box_pose(0.29))], extents, 0.01, voxel)
    np.testing.assert_array_equal(batch[0][0], points)
    assert np.all(np.abs(batch[1][0][:, 0] - 0.29) <= 0.11)

    store._crop = image_crop
    beyond = _box_pose(HELD_MARGIN_M + 0.001)  # its box's far end lies 1 mm outside the held one
    for pose, margin, size in ((beyond, 0.0, voxel), (_box_pose(0.01), 0.0, 0.01), (_box_pose(0.01), 0.0, None)):
        got, expected = store.crop("a", pose, extents, margin, size), plain.crop("a", pose, extents, margin, size)
        np.testing.assert_array_equal(got[0], expected[0])
        np.testing.assert_array_equal(got[1], expected[1])
    # a batch with a frame held and one not: each as one by one
    batch = store.crops([("a", _box_pose(0.01)), ("c", _box_pose(0.01))], extents, 0.01, voxel)
    np.testing.assert_array_equal(batch[0][0], points)
    np.testing.assert_array_equal(batch[1][0], plain.crop("c", _box_pose(0.01), extents, 0.01, voxel)[0])
    assert sequence.reads == 3  # a, b and c, each once


class _VariedSequence(_WallSequence):
    """A wall whose depth differs per frame (1 m + frame number mm); frames named "bad*" fail to read."""

    def depth(self, frame_id: str) -> np.ndarray:
        from sequences.errors import InputError

        self.reads += 1
        if frame_id.startswith("bad"):
            raise InputError(f"/seq/depth/{frame_id}.png", "unreadable or corrupt image")
        return np.full((self.camera.height, self.camera.width), 1.0 + int(frame_id) / 1000, np.float32)


def test_frames_preloaded_on_threads_equal_frames_read_one_by_one():
    ids = ["3", "bad1", "1", "7", "3", "bad0", "2"]  # a repeat and two unreadable frames
    one, threaded = _VariedSequence(1.0), _VariedSequence(1.0)
    loop = FrameStore(one, stride=2, colors=True)
    for f in ids:
        loop.image(f)
    store = FrameStore(threaded, stride=2, colors=True)
    store.image("7")  # kept already: not read again
    store.preload(ids, threads=2)
    assert threaded.reads == 6, "each frame read once, the kept one not again"
    for f in set(ids):
        depth, color = store.image(f)
        assert np.array_equal(depth, loop.image(f)[0]) and depth.dtype == np.float32
        assert (color is None) == (loop.image(f)[1] is None)
        if color is not None:
            assert np.array_equal(color, loop.image(f)[1])
    assert threaded.reads == 6, "image() serves the preloaded frames"
    assert float(store.image("2")[0][0, 0]) == np.float32(1.002)
    # the read errors, noted in the order given, the unreadable frames empty
    assert list(store.errors) == ["bad1", "bad0"] and store.errors == loop.errors
    assert not store.image("bad1")[0].any()
    # without a cache nothing would be kept: nothing is read
    uncached = _VariedSequence(1.0)
    FrameStore(uncached, stride=2, cache=False).preload(ids, threads=2)
    assert uncached.reads == 0


def test_a_model_of_frames_at_poses_seen_before_reuses_their_parts_and_is_the_same_bit_for_bit():
    from annotate.tracking.config import TrackingConfig
    from annotate.tracking.tracker import Tracker

    def fresh() -> Tracker:
        return Tracker(FrameStore(_WallSequence(1.0), stride=2, colors=True), np.array([0.2, 0.1, 0.1]), False, TrackingConfig(workers=1))

    ids, poses = ["a", "b", "c"], [_box_pose(0.05), _box_pose(0.02), _box_pose(-0.01)]
    tracker, plain = fresh(), fresh()
    first, again, reference = tracker.new_model(), tracker.new_model(), plain.new_model()
    tracker.add_frames_to_model(first, ids, poses)
    crops = []
    real = tracker.store.crops
    tracker.store.crops = lambda requests, *a, **k: crops.append([f for f, _ in requests]) or real(requests, *a, **k)
    # frame "b" at another pose (one ulp off in x) is cropped again; "a" and "c" at their poses are not
    moved = poses[1].copy()
    moved[0, 3] = np.nextafter(moved[0, 3], 1.0)
    tracker.add_frames_to_model(again, ids, [poses[0], moved, poses[2]])
    assert crops == [["b"]]
    plain.add_frames_to_model(reference, ids, [poses[0], moved, poses[2]])  # no part kept before: all from the crops
    assert len(again) > 0 and again.frames == reference.frames == 3
    for name in ("keys", "sum_xyz", "sum_rgb", "sum_view", "count", "hits"):
        assert np.array_equal(getattr(again, name), getattr(reference, name)), name
    # a model with another grid (a coarser voxel) does not take these parts
    coarse = Tracker(tracker.store, tracker.extents, False, TrackingConfig(workers=1, voxel_size=0.008))
    crops.clear()
    coarse.add_frames_to_model(coarse.new_model(), ids, poses)
    assert crops == [ids]


def test_the_kept_model_parts_stay_within_their_byte_budget(monkeypatch):
    import annotate.tracking.tracker as tracking
    from annotate.tracking.config import TrackingConfig

    tracker = tracking.Tracker(FrameStore(_WallSequence(1.0), stride=2, colors=True), np.array([0.2, 0.1, 0.1]), False, TrackingConfig(workers=1))
    ids, poses = ["a", "b", "c"], [_box_pose(0.05), _box_pose(0.02), _box_pose(-0.01)]
    tracker.add_frames_to_model(tracker.new_model(), ids[:1], poses[:1])
    one = tracking._nbytes(next(iter(tracker.store.model_parts.values())))
    monkeypatch.setattr(tracking, "MODEL_PART_BYTES", 2 * one)
    tracker.add_frames_to_model(tracker.new_model(), ids, poses)
    kept = tracker.store.model_parts
    assert list(k[0] for k in kept) == ["b", "c"]  # the least recently used ("a") dropped
    assert sum(tracking._nbytes(p) for p in kept.values()) <= 2 * one
