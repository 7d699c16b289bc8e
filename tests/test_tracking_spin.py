"""The spin about a symmetric object's y, weighed by what the registration measured of it (tracker.py).

A round cylinder's points turned about its axis still lie on it: the registration measures no spin, and the
predicted spin is kept. An elliptic cylinder's turned points leave it: the registration measures the spin, and its
own is kept. Truth: the spin each point set was turned by.
"""

from __future__ import annotations

import numpy as np
import pytest

from annotate.tracking.registration import ModelTarget
from annotate.tracking.tracker import SPIN_PRIOR_DEG, measured_spin, spin_information

SIGMA = 0.002  # point noise the information is scaled by (m), as TrackingConfig.information_sigma
DISTANCE = 0.004  # correspondence cut (m), as the fine stage's


def spin_y(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def cylinder(a: float, b: float, count: int, seed: int, noise: float = 0.0) -> np.ndarray:
    """Points (count, 3) on the side of a cylinder about y with semi-axes ``a`` (x) and ``b`` (z), 12 cm tall."""
    rng = np.random.default_rng(seed)
    t, y = rng.uniform(0, 2 * np.pi, count), rng.uniform(-0.06, 0.06, count)
    points = np.column_stack([a * np.cos(t), y, b * np.sin(t)])
    return points + rng.normal(0, noise, points.shape)


def seen_half(points: np.ndarray) -> np.ndarray:
    """The points a camera on -z sees (the surface facing it), about what one frame holds."""
    return points[points[:, 2] < 0][:800]


@pytest.mark.parametrize("noise", [0.0, 0.001])
def test_a_surface_of_revolution_measures_no_spin_and_keeps_the_prediction(noise):
    target = ModelTarget(cylinder(0.04, 0.04, 20000, seed=1, noise=noise), voxel_size=0.003)
    frame = seen_half(cylinder(0.04, 0.04, 4000, seed=2, noise=noise))
    information = spin_information(frame, target, DISTANCE, SIGMA)
    prior = np.radians(SPIN_PRIOR_DEG) ** -2
    assert information < 0.1 * prior, "the turned points still lie on the cylinder"
    registered = np.eye(4)
    registered[:3, :3] = spin_y(6.0)  # the registration's spin, free on a cylinder
    registered[:3, 3] = [0.01, 0.02, 0.5]
    out = measured_spin(registered, np.eye(4), information)
    spin = np.degrees(np.arctan2(out[0, 2], out[2, 2]))
    assert abs(spin) < 0.6, f"the prediction's spin (0 deg) is kept, got {spin:.2f} deg"
    np.testing.assert_allclose(out[:3, 1], registered[:3, 1], atol=1e-12)
    np.testing.assert_allclose(out[:3, 3], registered[:3, 3])


def test_a_flattened_cylinder_measures_its_spin_and_keeps_its_own():
    target = ModelTarget(cylinder(0.05, 0.02, 20000, seed=3, noise=0.001), voxel_size=0.003)
    frame = seen_half(cylinder(0.05, 0.02, 4000, seed=4, noise=0.001))
    information = spin_information(frame, target, DISTANCE, SIGMA)
    prior = np.radians(SPIN_PRIOR_DEG) ** -2
    # turned points leave a flattened cylinder: one frame fixes its spin better than the motion predicts it
    assert information > 1.5 * prior
    registered = np.eye(4)
    registered[:3, :3] = spin_y(6.0)
    out = measured_spin(registered, np.eye(4), information)
    spin = np.degrees(np.arctan2(out[0, 2], out[2, 2]))
    expected = 6.0 * information / (information + prior)  # a Gaussian posterior's mean
    assert spin == pytest.approx(expected, abs=1e-6)
    assert spin > 3.6, "most of the registration's own spin (6 deg) is kept"


def test_the_spin_is_weighed_about_the_y_the_registration_found():
    # a registration tilted 4 deg about x and spun 10 deg from a prediction: the tilt stays, only the spin is weighed
    tilt = np.eye(4)
    c, s = np.cos(np.radians(4.0)), np.sin(np.radians(4.0))
    tilt[:3, :3] = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    registered = tilt.copy()
    registered[:3, :3] = tilt[:3, :3] @ spin_y(10.0)
    half = measured_spin(registered, np.eye(4), np.radians(SPIN_PRIOR_DEG) ** -2)  # as certain as the prior: halfway
    np.testing.assert_allclose(half[:3, 1], registered[:3, 1], atol=1e-12)
    turn = tilt[:3, :3].T @ half[:3, :3]
    # closest_about_y keeps the spin nearest the prediction's; the rest of the 10 deg is weighed by half
    assert np.degrees(np.arctan2(turn[0, 2], turn[2, 2])) == pytest.approx(5.0, abs=0.05)


def test_no_points_measure_no_spin():
    target = ModelTarget(cylinder(0.04, 0.04, 2000, seed=5), voxel_size=0.003)
    assert spin_information(np.zeros((0, 3)), target, DISTANCE, SIGMA) == 0.0
