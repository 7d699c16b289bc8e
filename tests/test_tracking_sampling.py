"""sampling.every_kth: the fewest k that leaves at most the asked count."""

import numpy as np

from annotate.tracking.sampling import every_kth


def test_every_kth_row_bounds_the_count_with_the_fewest_k():
    rows = np.arange(30).reshape(10, 3)
    assert every_kth(rows, 0) is rows and every_kth(rows, 10) is rows and every_kth(rows, 50) is rows
    assert np.array_equal(every_kth(rows, 9), rows[::2])  # k = 2 leaves 5
    assert np.array_equal(every_kth(rows, 3), rows[::4])  # k = 3 would leave 4: k = 4 leaves 3
    assert np.array_equal(every_kth(rows, 1), rows[::10])
