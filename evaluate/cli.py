"""``evaluate``: evaluate pose-and-shape methods against REDWOOD75-format ground truth.

    evaluate --dataset DIR [--frames ROOT] --method SPEC [--method SPEC ...] --out OUT [--config FILE]
        [--workers N | --cluster ADDRESS] [--redo] [--json]

writes ``OUT/results.json``, ``OUT/table.md``, ``OUT/table.csv``, ``OUT/precision_curves.png``,
``OUT/curves.json``, ``OUT/errors.csv``, and NOCS-style mAP's ``OUT/nocs_map.csv`` and
``OUT/nocs_map_curves.png`` (see :mod:`evaluate.report`); options on the command line override the config file
(:mod:`evaluate.config`). Methods run here on the frames predict in chunks of samples on N local processes or a
Dask cluster (:mod:`evaluate.units`; ``--workers 1``: in this process), their predictions kept in ``OUT/.batch``
for a rerun; the results are those of one loop. ``--json`` prints the report on stdout.
"""

from __future__ import annotations

import argparse
import os
import sys

from batch.options import engine_problem
from evaluate import PRELOAD
from sequences.errors import InputError, run_cli

#: Method specs that are look-ups in this process (evaluate.methods.get_method): the oracle and predictions files.
LOOKUP_SUFFIXES = (".jsonl", ".json", ".ndjson")

EXAMPLES = """examples:
  evaluate --dataset ../shared/data/redwood75 --method spd=spd.jsonl --method oracle --out results/
  evaluate --dataset gt/ --frames sequences/ --method box --method template --out results/
  evaluate --dataset gt/ --frames sequences/ --method sgpa=cpas_toolbox.cpas_methods.sgpa:SGPA --out results/
  evaluate --config evaluate.yaml --out results/   (the YAML keys: see evaluate/config.py)
  evaluate --dataset gt/ --frames sequences/ --method template --out results/ --cluster tcp://HOST:8786 --json

outputs: OUT/results.json, OUT/table.md, OUT/table.csv, OUT/precision_curves.png, OUT/curves.json, OUT/errors.csv,
         OUT/nocs_map.csv, OUT/nocs_map_curves.png (NOCS-style mAP)"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evaluate",
        description="Evaluate methods on a REDWOOD75-format dataset (or a NOCS REAL275-format folder).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--dataset", help="folder with annotations.json and the meshes")
    parser.add_argument("--frames", help="root of the sequence folders (for methods run here)")
    parser.add_argument("--method", action="append", help="built-in name (box, template, oracle), NAME=predictions.jsonl or NAME=module:Class; repeatable; replaces the config's methods")
    parser.add_argument("--out", help="output folder")
    parser.add_argument("--config", help="YAML config; command-line options override it")
    parser.add_argument("--fscore-threshold", type=float, help="F-score distance threshold, m (default 0.01)")
    parser.add_argument("--surface-samples", type=int, help="points sampled per surface for chamfer distance and F-score (default 10000)")
    parser.add_argument("--seed", type=int, help="seed of the surface sampling (default 0)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--workers", type=int, metavar="N", help="methods run here: chunks of samples at once on local processes (default: the cores available)")
    parser.add_argument("--cluster", metavar="ADDRESS", help="methods run here: run the chunks on the Dask cluster whose scheduler is at ADDRESS "
                        "(tcp://HOST:8786; the workers must see the dataset, the frames and OUT at the same paths)")
    parser.add_argument("--redo", action="store_true", help="also predict the chunks an earlier run finished (by default their predictions in OUT/.batch are reused)")
    parser.add_argument("--json", action="store_true", help="print the report (results.json's content, the outputs, notes and units) as JSON on stdout, and nothing else there")
    return parser


def main(argv: list[str] | None = None) -> int:
    from batch.report import json_report

    args = build_parser().parse_args(argv)
    with json_report("evaluate", args.json) as stdout:
        return _main(args, stdout)


def _main(args, stdout) -> int:
    import json
    import time

    from batch.local import available_cores
    from batch.report import write_json

    start = time.perf_counter()
    problem = engine_problem(args.workers, args.cluster)
    if problem:
        raise InputError(None, problem)
    if args.seed is not None and args.seed < 0:
        raise InputError("--seed", "must be a non-negative integer")
    if not args.config:
        _start_early(args, {})
    from evaluate.config import build_config, read_config_file
    from evaluate.units import batch_predictor

    file_values = read_config_file(args.config) if args.config else {}
    if args.config:
        _start_early(args, file_values)
    config = build_config(args, file_values)

    from evaluate.report import nocs_labels, nocs_values, write_outputs
    from evaluate.runner import evaluate_dataset

    _check_out(config.out)  # before a long run, not after it
    units: dict = {}
    predict = batch_predictor(config, args.workers or available_cores(), args.cluster, args.redo, args.quiet, units)
    evaluation = evaluate_dataset(config, progress=not args.quiet, predict=predict)
    paths = write_outputs(config.out, evaluation.dataset.name, evaluation.results, evaluation.dataset.categories, evaluation.notes)
    for note in evaluation.notes:
        print(f"note: {note}", file=sys.stderr)
    for result in evaluation.results:
        headline = ", ".join(f"{p.label}: {'–' if p.overall is None else f'{100 * p.overall:.1f}%'}" for p in result.precision)
        print(f"{result.name}: {headline} ({len(result.failed)} of {result.samples} failed)")
        if result.nocs is not None:
            mean, _ = nocs_values(result.nocs)
            print(f"{result.name} NOCS mAP: " + ", ".join(f"{label} {'–' if v != v else f'{100 * v:.1f}%'}" for label, v in zip(nocs_labels(result.nocs), mean)))
    print(f"wrote {', '.join(str(p) for p in paths.values())}")
    if args.json:
        results = json.loads((config.out / "results.json").read_text())
        write_json({"command": "evaluate", "out": str(config.out), "seconds": round(time.perf_counter() - start, 3), "outputs": {k: str(v) for k, v in paths.items()},
                    "notes": evaluation.notes, "results": results, "batch": units}, stdout)
    return 0


def _start_early(args, file_values: dict) -> None:
    """Start the local processes' server now where a batch will run on them: its imports then overlap this
    process's (the dataset, the metrics) instead of following them."""
    from batch.local import available_cores, start_server

    if not args.cluster and (args.workers or available_cores()) > 1 and any(_runs_here(spec) for spec in _specs(args, file_values)):
        start_server(PRELOAD)


def _specs(args, file_values: dict) -> list:
    """The method specs as given (the command line's, else the config file's), before they are checked."""
    if args.method:
        return list(args.method)
    return [m.get("spec") if isinstance(m, dict) else m for m in file_values.get("methods") or []]


def _runs_here(spec) -> bool:
    """Whether a method spec runs on the frames here (a batch's units), as evaluate.methods.get_method reads it:
    not the oracle, not NAME=predictions file."""
    if not isinstance(spec, str):
        return False
    name, target = (part.strip() for part in spec.split("=", 1)) if "=" in spec else (None, spec.strip())
    return not (target == "oracle" or target.lower().endswith(LOOKUP_SUFFIXES) or (name is not None and ":" not in target and target not in ("box", "template")))


def _check_out(out) -> None:
    """Fail before a long run, not after it, when OUT cannot be written (nothing is created here)."""
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    existing = out
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK):
        raise InputError(out, f"cannot write the output folder ({existing} is not writable)")


def entry() -> None:
    raise SystemExit(run_cli(main))


if __name__ == "__main__":
    entry()
