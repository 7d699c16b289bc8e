"""Generated input for every parser of the commands: each input loads or ends in one line (InputError), never a traceback.

    .venv/bin/python benchmarks/fuzz_parsers.py [--examples 10000]

Parsers: the annotation document (YAML text: random structures, dumped, then mutated: bytes cut, duplicated keys,
aliases, deep nesting), camera.yaml, the evaluate config, a predictions file's lines, and a REDWOOD75
annotations.json as a dataset. Prints per parser the inputs tried, how many loaded, how many were refused in one
line, and any other exception (the goal: none).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import yaml  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from sequences.errors import InputError  # noqa: E402

SCALARS = st.none() | st.booleans() | st.floats(allow_nan=True, allow_infinity=True) | st.integers(-10**15, 10**15) | st.text(max_size=12)
VALUES = st.recursive(SCALARS, lambda c: st.lists(c, max_size=5) | st.dictionaries(st.text(max_size=10) | st.integers(), c, max_size=5), max_leaves=40)
KEYS = ["sequence", "category", "symmetry", "extents", "frames", "position", "orientation", "source", "fx", "fy", "cx", "cy", "width",
        "height", "depth_scale", "dataset", "method", "out", "thresholds", "0000001", "0000002"]
DOCUMENTS = st.recursive(SCALARS, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.sampled_from(KEYS) | st.text(max_size=6), c, max_size=6),
                         max_leaves=40)


def mutate(text: str, draw) -> str:
    """Damage a document's text the ways files get damaged or crafted: cut short, a key repeated, an alias, deep nesting."""
    kind = draw(st.sampled_from(["none", "cut", "duplicate", "alias", "deep", "bytes"]))
    if kind == "cut" and text:
        return text[: draw(st.integers(0, len(text)))]
    if kind == "duplicate":
        return text + text
    if kind == "alias":
        return "a: &a [1, 2, 3]\nb: [*a, *a, *a]\n" + text
    if kind == "deep":
        return "x: " + "[" * draw(st.integers(60, 5000)) + "]" * 5000 + "\n"
    if kind == "bytes":
        return draw(st.text(max_size=200))
    return text


def run(name: str, parse, strategy, examples: int) -> Counter:
    outcomes: Counter = Counter()

    @settings(max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(strategy, st.data())
    def one(value, data):
        text = yaml.safe_dump(value) if not isinstance(value, str) else value
        text = mutate(text, data.draw)
        try:
            parse(text)
            outcomes["loaded"] += 1
        except InputError as error:
            outcomes["refused in one line" if "\n" not in str(error) else "refused, several lines"] += 1
        except Exception as error:  # the goal is none of these
            outcomes[f"{error.__class__.__name__}: {str(error)[:80]}"] += 1

    started = time.perf_counter()
    one()
    print(f"{name:22s} {sum(outcomes.values()):6d} inputs in {time.perf_counter() - started:5.1f} s: " + ", ".join(f"{k} {v}" for k, v in outcomes.most_common()), flush=True)
    return outcomes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=10_000)
    args = parser.parse_args()
    from evaluate.config import read_config_file
    from evaluate.datasets.redwood75 import Redwood75Dataset
    from evaluate.methods.predictions import PredictionsFile
    from sequences.annotation import load_annotation
    from sequences.camera import Camera

    work = Path(tempfile.mkdtemp(prefix="fuzz-"))

    def through(file_name: str, reader):
        def parse(text: str):
            path = work / file_name
            path.write_text(text)
            return reader(path)
        return parse

    def dataset(path: Path):
        folder = work / "dataset"
        folder.mkdir(exist_ok=True)
        (folder / "annotations.json").write_text(path.read_text())
        return Redwood75Dataset(folder)

    def predictions(path: Path):
        return PredictionsFile("fuzz", path)

    json_text = DOCUMENTS.map(lambda v: __import__("json").dumps(v, default=str))
    failures = 0
    for name, parse, strategy in (
        ("annotation document", through("annotation.yaml", load_annotation), DOCUMENTS),
        ("camera.yaml", through("camera.yaml", Camera.from_yaml), DOCUMENTS),
        ("evaluate config", through("config.yaml", read_config_file), DOCUMENTS),
        ("predictions lines", through("predictions.jsonl", predictions), json_text),
        ("REDWOOD75 dataset", through("annotations.json", dataset), json_text),
    ):
        outcomes = run(name, parse, strategy, args.examples)
        failures += sum(v for k, v in outcomes.items() if k not in ("loaded", "refused in one line"))
    print(f"other outcomes (tracebacks) over all parsers: {failures}")
    return 0 if failures == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
