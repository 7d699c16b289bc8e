"""Synthetic RGB-D sequences with known truth: ``python -m sequences.synth OUT --category C``.

A procedural (or given) object is carried through all orientations 0.5-0.85 m in front of a
PrimeSense-like camera (into its opening and at its bottom too) by a hand that occludes it and
regrasps it so that what it covered is seen free in another grasp, in front of a person, a wall
and a table. The sequence is written in Redwood's layout with its truth in ``OUT/truth/``.
"""

from .truth import Truth, load_truth, truth_annotation


def __getattr__(name: str):
    # the renderer (open3d) is imported on first use, so ``python -m sequences.synth`` rejects bad input fast
    if name == "generate_sequence":
        from .generate import generate_sequence

        return generate_sequence
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["generate_sequence", "load_truth", "truth_annotation", "Truth"]
