"""Synthetic RGB-D sequences with known truth: ``python -m sequences.synth OUT --category C``.

A procedural (or given) object is carried through all orientations 0.5-0.85 m in front of a
PrimeSense-like camera by a hand that occludes it and regrasps it, in front of a person, a wall
and a table. The sequence is written in Redwood's layout with its truth in ``OUT/truth/``.
"""

from .generate import generate_sequence
from .truth import Truth, load_truth, truth_annotation

__all__ = ["generate_sequence", "load_truth", "truth_annotation", "Truth"]
