"""A chain's steps (propagate.run_chain): which registered frames it follows, against a scripted registration."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from annotate.tracking import TrackingConfig
from annotate.tracking.propagate import follows, run_chain
from annotate.tracking.tracker import FrameResult


def _pose(x_m: float, turn_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", turn_deg, degrees=True).as_matrix()
    T[:3, 3] = [x_m, 0.0, 0.5]
    return T


class ScriptedTracker:
    """Registers frame f to ``answers[f]`` (pose, fitness) whatever the start; records starts and model additions."""

    def __init__(self, answers: dict[str, tuple[np.ndarray, float]], config: TrackingConfig) -> None:
        self.answers, self.config = answers, config
        self.starts: dict[str, np.ndarray] = {}
        self.added: list[str] = []

    def new_model(self) -> object:
        return object()

    def add_to_model(self, model: object, frame_id: str, pose: np.ndarray) -> None:
        self.added.append(frame_id)

    def register(self, frame_id: str, init_pose: np.ndarray, model: object, refresh_every: int = 1) -> FrameResult:
        self.starts[frame_id] = init_pose.copy()
        pose, fitness = self.answers[frame_id]
        return FrameResult(pose.copy(), True, {"fitness": fitness})


def test_a_chain_follows_a_frame_below_min_fitness_that_stayed_near_its_start_and_not_a_lost_one():
    config = TrackingConfig()  # min_fitness 0.5, follows down to 0.2 within 5 deg / 10 mm
    answers = {
        "b": (_pose(0.01), 0.9),  # fits the model: followed
        "c": (_pose(0.02), 0.3),  # a new side turned to the camera: low fitness, where the prediction put it
        "d": (_pose(0.03, 31.0), 0.3),  # as low, but 30 deg from where it started: the registration ran off
        "e": (_pose(0.04, 2.0), 0.1),  # below chain_follow_fitness
        "f": (_pose(0.035, 2.0), 0.25),  # 5 mm and 2 deg from its start
    }
    tracker = ScriptedTracker(answers, config)
    results = run_chain(tracker, ["a", "b", "c", "d", "e", "f"], _pose(0.0))
    assert list(results) == ["b", "c", "d", "e", "f"]
    assert tracker.added == ["a", "b", "c", "f"]
    np.testing.assert_allclose(tracker.starts["c"], _pose(0.02), atol=1e-12)  # 1 cm per frame
    # d and e were not followed: the chain predicts on from b and c, three and four frames on
    np.testing.assert_allclose(tracker.starts["d"], _pose(0.03), atol=1e-12)
    np.testing.assert_allclose(tracker.starts["e"], _pose(0.03), atol=1e-12)
    np.testing.assert_allclose(tracker.starts["f"], _pose(0.03), atol=1e-12)


def test_the_follow_rule_off_takes_only_frames_at_min_fitness():
    config = TrackingConfig(chain_follow_fitness=0.5)
    start = _pose(0.0)
    assert not follows(FrameResult(_pose(0.001), True, {"fitness": 0.49}), start, config)
    assert follows(FrameResult(_pose(0.05, 40.0), True, {"fitness": 0.5}), start, config)  # min_fitness alone decides
    assert not follows(FrameResult(_pose(0.0), False, {"fitness": 0.9}), start, config)  # a failed registration
    on = TrackingConfig()
    assert follows(FrameResult(_pose(0.001), True, {"fitness": 0.49}), start, on)
    assert not follows(FrameResult(_pose(0.011), True, {"fitness": 0.49}), start, on)  # 11 mm from its start
    assert not follows(FrameResult(_pose(0.0, 5.5), True, {"fitness": 0.49}), start, on)  # 5.5 deg
