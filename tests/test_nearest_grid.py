"""nearest_grid.CellGrid: the exact k nearest points within a reach, against brute force and scipy's KD-tree."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from annotate.tracking import nearest_grid
from annotate.tracking.nearest_grid import CellGrid
from annotate.tracking.registration import ModelTarget


def _brute(points: np.ndarray, queries: np.ndarray, k: int, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest by sorting all squared distances (summed as the grid sums them), the lower index first among
    equals; missing: inf and len(points)."""
    d2 = ((queries[:, None, 0] - points[None, :, 0]) ** 2 + (queries[:, None, 1] - points[None, :, 1]) ** 2) + (queries[:, None, 2] - points[None, :, 2]) ** 2
    order = np.lexsort((np.broadcast_to(np.arange(len(points)), d2.shape), d2), axis=1)[:, :k]
    near = np.take_along_axis(d2, order, axis=1)
    inside = near < reach * reach
    return np.where(inside, np.sqrt(near), np.inf), np.where(inside, order, len(points))


def _voxel_model(seed: int) -> np.ndarray:
    """Voxel centroids (one per 3 mm voxel) of noisy points on two plates at an angle, m: a model like the tracker's."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(-0.06, 0.06, (2, 8000))
    plate = np.stack([u, v, 0.002 * rng.normal(size=8000)], axis=1)
    tilted = plate[:4000] @ np.array([[1.0, 0, 0], [0, 0.6, 0.8], [0, -0.8, 0.6]]).T + [0.0, 0.03, 0.02]
    points = np.concatenate([plate[4000:], tilted])
    keys, inverse = np.unique(np.floor(points / 0.003).astype(np.int64), axis=0, return_inverse=True)
    sums = np.zeros((len(keys), 3))
    np.add.at(sums, inverse.ravel(), points)
    return sums / np.bincount(inverse.ravel())[:, None]


@pytest.mark.parametrize("cell", [0.003, 0.009, 0.02])
def test_the_k_nearest_within_reach_equal_brute_force(cell):
    model = _voxel_model(0)
    rng = np.random.default_rng(1)
    queries = np.concatenate([
        model[rng.integers(0, len(model), 600)] + rng.normal(size=(600, 3)) * 0.004,  # near the surface
        rng.uniform(model.min(0) - 0.04, model.max(0) + 0.04, (400, 3)),  # anywhere around it, outside the grid too
        [[1.0, 1.0, 1.0], [-0.5, 0.0, 0.0]],  # far away
    ])
    grid = CellGrid(model, cell)
    for k, reach in ((5, 0.015), (1, 0.004), (3, 0.05)):
        distance, index = grid.query(queries, k, reach)
        want_distance, want_index = _brute(model, queries, k, reach)
        assert np.array_equal(index, want_index)
        assert np.array_equal(distance, want_distance)  # the same sums, the same square roots
        tree_distance, tree_index = cKDTree(model).query(queries, k=k, distance_upper_bound=reach)
        assert np.array_equal(index.reshape(tree_index.shape), tree_index)  # no ties here: the KD-tree agrees
        np.testing.assert_allclose(distance.reshape(tree_distance.shape), tree_distance, rtol=1e-12)
    assert np.isinf(grid.query(queries[-2:], 5, 0.015)[0]).all()


def test_ties_go_to_the_lower_index_and_the_reach_is_strict():
    points = np.array([[0.0, 0.0, 0.0], [0.002, 0.0, 0.0], [-0.002, 0.0, 0.0], [0.0, 0.0, 0.004]])
    grid = CellGrid(points, 0.003)
    distance, index = grid.query(np.array([[0.0, 0.0, 0.0]]), 4, 0.004)
    assert index.tolist() == [[0, 1, 2, 4]]  # 1 and 2 tie at 2 mm; 3 lies at the reach itself: not within it
    assert distance[0, :3].tolist() == [0.0, 0.002, 0.002] and distance[0, 3] == np.inf
    duplicates = CellGrid(np.array([[0.01, 0.0, 0.0]] * 3), 0.003)
    assert duplicates.query(np.zeros((1, 3)), 2, 0.02)[1].tolist() == [[0, 1]]


def test_an_empty_grid_and_a_spread_out_one():
    empty = CellGrid(np.zeros((0, 3)), 0.003)
    distance, index = empty.query(np.zeros((2, 3)), 3, 0.01)
    assert np.isinf(distance).all() and (index == 0).all()
    # two clusters a kilometre apart: the cells grow (MAX_CELLS), the answers stay exact
    rng = np.random.default_rng(3)
    points = np.concatenate([rng.normal(size=(200, 3)) * 0.01, rng.normal(size=(200, 3)) * 0.01 + 1000.0])
    grid = CellGrid(points, 0.003)
    assert np.prod(grid.dims) <= nearest_grid.MAX_CELLS and grid.cell > 0.003
    queries = points[rng.integers(0, 400, 100)] + rng.normal(size=(100, 3)) * 0.002
    assert np.array_equal(grid.query(queries, 4, 0.01)[1], _brute(points, queries, 4, 0.01)[1])


@pytest.mark.parametrize("cell", [0.0, -1.0, float("nan"), float("inf")])
def test_a_bad_cell_size_is_refused(cell):
    with pytest.raises(ValueError, match="cell size"):
        CellGrid(np.zeros((3, 3)), cell)


def test_model_target_nearest_answers_as_the_kd_tree():
    model = _voxel_model(2)
    target = ModelTarget(model, voxel_size=0.003)
    rng = np.random.default_rng(4)
    queries = model[rng.integers(0, len(model), 500)] + rng.normal(size=(500, 3)) * 0.003
    distance, index = target.nearest(queries, 0.004)
    want_distance, want_index = cKDTree(model).query(queries, distance_upper_bound=0.004)
    assert np.array_equal(index, want_index)
    np.testing.assert_allclose(distance, want_distance, rtol=1e-12)
    assert 0 < np.isinf(distance).sum() < len(queries)  # both kinds of answer occur
