"""Batches: independent units of work (sequences; method x sample chunks) run on local processes or a Dask cluster.

``annotate --track SEQ...``, ``reconstruct-sequence SEQ...`` and ``evaluate`` cut their work into units and hand
them to :func:`run_batch`, which

1. skips the units that a previous run finished (:mod:`batch.units`: a finished marker, written last),
2. runs the others on local processes (:mod:`batch.local`, the default: one fresh process per unit, at most N at
   once) or on a Dask cluster given by its address (:mod:`batch.cluster`), with a progress bar of units done and
   time left,
3. runs the units' ordered second steps, where a unit has one, one at a time in the units' order,
4. writes each finished unit's marker and returns a report (:mod:`batch.report`; ``--json`` prints it).

A unit's bad input or bug fails that unit alone (its one line is reported), and so does a worker that dies
while running it; the others go on. Outputs do not depend on the worker count or the engine: every unit runs
single-threaded (BLAS, OpenMP) on its own inputs, and what units share (an export folder's index, its scene
numbers) is ordered by the units' order, not by which finishes first.

A command starts its local processes' server first thing (:func:`batch.local.start_server`), before its own
imports and its work list: on two cores the server's imports then overlap the command's.
"""

from .runner import Batch, run_batch
from .units import Outcome, Unit

__all__ = ["Batch", "Outcome", "Unit", "run_batch"]
