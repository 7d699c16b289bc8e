"""config.scaled_to: the voxel an object is tracked on, from its box and its symmetry."""

from __future__ import annotations

import pytest

from annotate.tracking.config import SHALLOW_RATIO, TrackingConfig, scaled_to


def test_a_shallow_body_of_symmetry_y_gets_the_finer_voxel():
    config = TrackingConfig()
    bowl = [0.140, 0.041, 0.140]  # a bowl's box (m): a rim and a foot 41 mm apart
    assert scaled_to(config, bowl, symmetric=True).voxel_size == config.shallow_voxel_size == 0.003
    # the same box without symmetry, a can or a bottle (tall), a mug (no symmetry): the usual voxel
    assert scaled_to(config, bowl, symmetric=False).voxel_size == config.voxel_size
    assert scaled_to(config, [0.072, 0.129, 0.072], symmetric=True).voxel_size == config.voxel_size
    assert scaled_to(config, [0.085, 0.095, 0.115], symmetric=False).voxel_size == config.voxel_size
    # the rule's edge: just under SHALLOW_RATIO of the width is shallow, at it is not
    assert scaled_to(config, [0.1, 0.1 * SHALLOW_RATIO - 1e-6, 0.1], symmetric=True).voxel_size == 0.003
    assert scaled_to(config, [0.1, 0.1 * SHALLOW_RATIO, 0.1], symmetric=True).voxel_size == config.voxel_size


def test_a_large_body_still_grows_its_voxel():
    config = TrackingConfig()
    assert scaled_to(config, [0.36, 0.05, 0.36], symmetric=True).voxel_size == pytest.approx(0.36 / config.voxels_across)
    assert scaled_to(config, [0.35, 0.25, 0.2]).voxel_size == pytest.approx(0.35 / config.voxels_across)
    off = TrackingConfig(shallow_voxel_size=0.0)
    assert scaled_to(off, [0.14, 0.04, 0.14], symmetric=True) is off  # 0: the rule is off, the configuration unchanged


def test_a_negative_shallow_voxel_is_refused():
    with pytest.raises(ValueError, match="shallow_voxel_size"):
        TrackingConfig(shallow_voxel_size=-0.001)
