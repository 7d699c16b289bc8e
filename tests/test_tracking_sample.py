"""Tracking the bundled sample headless (``annotate SAMPLE --track``'s engine) from three placed boxes, against its truth."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotate.tracking import track_sequence
from annotate.tracking.quality import pose_difference
from sequences.annotation import Annotation, FramePose
from sequences.reader import open_sequence
from sequences.synth import load_truth

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    try:
        from sequences.sample import sample_sequence

        source = sample_sequence()
    except Exception as error:
        pytest.skip(f"bundled sample unavailable: {error}")
    root = tmp_path_factory.mktemp("sample") / source.name
    shutil.copytree(source, root, ignore=shutil.ignore_patterns("annotation.yaml*"))
    return root


def _placed(truth, ids: list[str], seed: int) -> Annotation:
    """Boxes in frames 4, 31 and 57 as a person places them: within 2 deg and 3 mm of the truth, extents 4% large."""
    rng = np.random.default_rng(seed)
    annotation = Annotation(sequence="sample", category="mug", symmetry="none", extents=np.asarray(truth.extents) * 1.04)
    for frame_id in (ids[4], ids[31], ids[57]):
        T = truth.poses[frame_id].copy()
        turn = np.radians(2.0) * rng.uniform(0.5, 1) * Rotation.random(random_state=rng).as_rotvec() / np.pi
        T[:3, :3] = Rotation.from_rotvec(turn).as_matrix() @ T[:3, :3]
        T[:3, 3] += rng.uniform(-0.003, 0.003, 3)
        annotation.frames[frame_id] = FramePose.from_matrix(T, "manual")
    return annotation


@pytest.mark.parametrize("seed, median_deg", [(4, 3.0), (6, None)])
def test_no_frame_of_the_sample_is_far_off_without_a_flag(sample, seed, median_deg):
    truth = load_truth(sample)
    sequence = open_sequence(sample)
    ids = list(sequence.ids)
    tracked = track_sequence(sequence, _placed(truth, ids, seed))
    errors = np.array([pose_difference(truth.poses[f], tracked.frames[f].matrix)[0] for f in ids])
    flagged = np.array([bool(tracked.frames[f].extra.get("flagged")) for f in ids])
    print(f"sample: rotation median {np.median(errors):.2f} deg, p90 {np.percentile(errors, 90):.2f}, {flagged.sum()} of {len(ids)} flagged")
    # measured with the placement of seed 6: 8 frames more than 10 deg off that only the both-chains-jumped flag
    # catches (chains_jumped_deg; the chains' gap stays under its threshold there)
    assert not np.any((errors > 10.0) & ~flagged), [(f, round(e, 1)) for f, e, g in zip(ids, errors, flagged) if e > 10 and not g]
    if median_deg is not None:
        # measured: 2.15 deg median, p90 5.75, 28 of 60 flagged (the 60-frame mug is harder than the benchmark's
        # 100-frame ones; other placements 1.05-5.78 deg median)
        assert np.median(errors) < median_deg
