"""Shared test fixtures: paths to ../shared data (skipped with a reason where absent), and rendered scenes that
several tracking test modules use (rendered once per session)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def redwood75_dir() -> Path:
    path = SHARED / "redwood75"
    if not (path / "annotations.json").exists():
        pytest.skip(f"REDWOOD75 ground truth not found at {path} (../shared is absent)")
    return path


@pytest.fixture(scope="session")
def nocs_dir() -> Path:
    path = SHARED / "nocs_real_sample"
    if not path.exists():
        pytest.skip(f"NOCS sample not found at {path} (../shared is absent)")
    return path


@pytest.fixture(scope="session")
def rendered_mug(tmp_path_factory):
    """(sequence, mesh, truth) of the test mug, 24 frames without a hand (test_tracking_render)."""
    from test_tracking_render import mug_mesh, rendered_scene

    return rendered_scene(tmp_path_factory.mktemp("mug") / "mug_0002", mug_mesh(), frames=24, seed=3, hand=False)


@pytest.fixture(scope="session")
def rendered_camera(tmp_path_factory):
    """(sequence, mesh, truth) of a procedural camera, 12 frames without a hand (test_tracking_render)."""
    import numpy as np
    from test_tracking_render import rendered_scene

    from sequences.synth.shapes import procedural_mesh

    return rendered_scene(tmp_path_factory.mktemp("camera") / "camera_0001", procedural_mesh("camera", np.random.default_rng(3)), frames=12, seed=3, hand=False)


@pytest.fixture(scope="session")
def rendered_laptop(tmp_path_factory):
    """(sequence, mesh, truth) of a procedural laptop, 12 frames without a hand (test_tracking_render)."""
    import numpy as np
    from test_tracking_render import rendered_scene

    from sequences.synth.shapes import procedural_mesh

    return rendered_scene(tmp_path_factory.mktemp("laptop") / "laptop_0001", procedural_mesh("laptop", np.random.default_rng(4)), frames=12, seed=4, hand=False)
