"""The ``evaluate`` configuration: a YAML file, overridden by the command line.

Keys (all optional in the file; ``dataset``, ``out`` and at least one method must come from
somewhere)::

    dataset: path/to/dataset          # folder with annotations.json and the meshes
    frames: path/to/sequences         # root of the sequence folders (methods run here need it)
    out: path/to/results
    methods:                          # SPEC strings, or mappings {spec, name, config}
      - box
      - spd=spd_predictions.jsonl
      - {name: noisy, spec: oracle, config: {position_error: 0.01}}
    method_config: {box: {...}}       # configuration for methods named on the command line
    thresholds:                       # precision tuples; an absent key is an unused threshold
      - {position: 0.02, degrees: 10}
      - {position: 0.01, degrees: 5, fscore: 0.8}
    fscore_threshold: 0.01            # F-score distance threshold Delta, m
    surface_samples: 10000            # points sampled on each surface for chamfer distance and F-score
    seed: 0
    curves: {position: [...], degrees: [...], iou: [...], fscore: [...]}   # Fig. 5 grids

Relative paths in the file are relative to the file's folder; on the command line, to the
working folder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evaluate import metrics
from sequences.documents import load_mapping
from sequences.errors import InputError

THRESHOLD_KEYS = ("position", "degrees", "iou", "fscore")
#: The paper's threshold tuples (Table 2): (10 deg, 2 cm), (5 deg, 1 cm), with F-score >= 0.6 / 0.8.
DEFAULT_THRESHOLDS = tuple({k: (None if v is None else float(v)) for k, v in t.as_dict().items()} for t in metrics.DEFAULT_THRESHOLDS)
#: The grids of the paper's Fig. 5 (cpas_toolbox's redwood75.yaml), plus IoU.
DEFAULT_CURVES = {
    "position": metrics.POSITION_CURVE.tolist(),  # m
    "degrees": metrics.DEGREE_CURVE.tolist(),
    "iou": metrics.IOU_CURVE.tolist(),
    "fscore": metrics.FSCORE_CURVE.tolist(),
}
KEYS = ("dataset", "frames", "out", "methods", "method_config", "thresholds", "fscore_threshold", "surface_samples", "seed", "curves")


@dataclass
class MethodEntry:
    spec: str
    config: dict = field(default_factory=dict)
    base: Path | None = None  # folder relative predictions paths start from


@dataclass
class EvaluateConfig:
    dataset: Path
    out: Path
    methods: list[MethodEntry]
    frames: Path | None = None
    thresholds: list[dict] = field(default_factory=lambda: [dict(t) for t in DEFAULT_THRESHOLDS])
    fscore_threshold: float = metrics.DEFAULT_FSCORE_DISTANCE
    surface_samples: int = metrics.DEFAULT_SAMPLES
    seed: int = 0
    curves: dict[str, list[float]] = field(default_factory=lambda: {k: list(v) for k, v in DEFAULT_CURVES.items()})


def _number(path, key: str, value: Any, positive: bool = True, allow_zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(path, f"{key} must be a finite number, got {value!r}")
    if positive and (value < 0 or (value == 0 and not allow_zero)):
        raise InputError(path, f"{key} must be {'non-negative' if allow_zero else 'positive'}, got {value!r}")
    return float(value)


def parse_threshold(path, where: str, value: Any) -> dict:
    if not isinstance(value, dict):
        raise InputError(path, f"{where} must be a mapping with keys from {list(THRESHOLD_KEYS)}")
    unknown = sorted(set(value) - set(THRESHOLD_KEYS))
    if unknown:
        raise InputError(path, f"{where}: unknown keys {unknown}; expected {list(THRESHOLD_KEYS)}")
    out = {k: (None if value.get(k) is None else _number(path, f"{where}.{k}", value[k], allow_zero=True)) for k in THRESHOLD_KEYS}
    if all(v is None for v in out.values()):
        raise InputError(path, f"{where} uses no threshold")
    for k in ("iou", "fscore"):
        if out[k] is not None and out[k] > 1:
            raise InputError(path, f"{where}.{k} must be at most 1, got {out[k]}")
    return out


def _path(base: Path | None, value: Any, path, key: str) -> Path:
    if not isinstance(value, str) or not value:
        raise InputError(path, f"{key} must be a path, got {value!r}")
    p = Path(value).expanduser()
    return p if p.is_absolute() or base is None else base / p


def read_config_file(path: str | Path) -> dict:
    """The YAML file as a validated dict of :data:`KEYS` (paths resolved against its folder)."""
    path = Path(path)
    data = load_mapping(path, "config", KEYS, as_yaml=True)
    base = path.resolve().parent
    out: dict = {}
    for key in ("dataset", "frames", "out"):
        if data.get(key) is not None:
            out[key] = _path(base, data[key], path, key)
    method_config = data.get("method_config") or {}
    if not isinstance(method_config, dict) or not all(isinstance(v, dict) for v in method_config.values()):
        raise InputError(path, "method_config must map method names to mappings")
    out["method_config"] = {str(k): v for k, v in method_config.items()}
    if data.get("methods") is not None:
        methods = data["methods"]
        if not isinstance(methods, list) or not methods:
            raise InputError(path, "methods must be a non-empty list")
        out["methods"] = [_method_entry(path, base, i, m, out["method_config"]) for i, m in enumerate(methods)]
    if data.get("thresholds") is not None:
        thresholds = data["thresholds"]
        if not isinstance(thresholds, list) or not thresholds:
            raise InputError(path, "thresholds must be a non-empty list")
        out["thresholds"] = [parse_threshold(path, f"thresholds[{i}]", t) for i, t in enumerate(thresholds)]
    if data.get("fscore_threshold") is not None:
        out["fscore_threshold"] = _number(path, "fscore_threshold", data["fscore_threshold"])
    if data.get("surface_samples") is not None:
        out["surface_samples"] = _count(path, "surface_samples", data["surface_samples"])
    if data.get("seed") is not None:
        if isinstance(data["seed"], bool) or not isinstance(data["seed"], int) or data["seed"] < 0:
            raise InputError(path, f"seed must be a non-negative integer, got {data['seed']!r}")
        out["seed"] = data["seed"]
    if data.get("curves") is not None:
        out["curves"] = _curves(path, data["curves"])
    return out


def _count(path, key: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise InputError(path, f"{key} must be a positive integer, got {value!r}")
    return value


def _curves(path, value: Any) -> dict[str, list[float]]:
    if not isinstance(value, dict):
        raise InputError(path, "curves must be a mapping of position/degrees/iou/fscore to lists of thresholds")
    unknown = sorted(set(value) - set(THRESHOLD_KEYS))
    if unknown:
        raise InputError(path, f"curves: unknown keys {unknown}; expected {list(THRESHOLD_KEYS)}")
    curves = {k: list(v) for k, v in DEFAULT_CURVES.items()}
    for key, grid in value.items():
        if not isinstance(grid, list) or not grid:
            raise InputError(path, f"curves.{key} must be a non-empty list of numbers")
        curves[key] = [_number(path, f"curves.{key}", g, allow_zero=True) for g in grid]
    return curves


def _method_entry(path, base: Path, i: int, value: Any, method_config: dict) -> MethodEntry:
    if isinstance(value, str):
        name = value.split("=", 1)[0].strip() if "=" in value else value.strip()
        return MethodEntry(value, dict(method_config.get(name, {})), base)
    if isinstance(value, dict):
        unknown = sorted(set(value) - {"spec", "name", "config"})
        if unknown or not isinstance(value.get("spec"), str):
            raise InputError(path, f"methods[{i}] must be a SPEC string or a mapping with 'spec' (and optional 'name', 'config')")
        spec = value["spec"] if value.get("name") is None else f"{value['name']}={value['spec']}"
        config = value.get("config") or {}
        if not isinstance(config, dict):
            raise InputError(path, f"methods[{i}].config must be a mapping")
        return MethodEntry(spec, dict(config), base)
    raise InputError(path, f"methods[{i}] must be a SPEC string or a mapping")


def build_config(args, file_values: dict | None = None) -> EvaluateConfig:
    """Merge command-line ``args`` (argparse namespace; None = not given) over the file's values."""
    values = dict(file_values or {})
    method_config = values.pop("method_config", {})
    where = getattr(args, "config", None)
    for key in ("dataset", "frames", "out"):
        if getattr(args, key, None) is not None:
            values[key] = Path(getattr(args, key))
    if getattr(args, "method", None):
        values["methods"] = [MethodEntry(spec, dict(method_config.get(spec.split("=", 1)[0].strip(), {})), None) for spec in args.method]
    if getattr(args, "fscore_threshold", None) is not None:
        values["fscore_threshold"] = _number("--fscore-threshold", "F-score threshold", args.fscore_threshold)
    if getattr(args, "surface_samples", None) is not None:
        values["surface_samples"] = _count("--surface-samples", "surface samples", args.surface_samples)
    if getattr(args, "seed", None) is not None:
        values["seed"] = int(args.seed)
    for key, option in (("dataset", "--dataset"), ("out", "--out")):
        if key not in values:
            raise InputError(where, f"no {key}: give {option} or '{key}:' in the config")
    if not values.get("methods"):
        raise InputError(where, "no method: give --method or 'methods:' in the config")
    return EvaluateConfig(**values)

