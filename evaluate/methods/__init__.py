"""Methods to evaluate, resolved from a SPEC: a built-in name (``box``, ``template``, ``oracle``),
``NAME=predictions.jsonl`` (a predictions file), or ``[NAME=]module:Class`` (a class implementing our
:class:`~evaluate.methods.base.Method`, or one with cpas_toolbox's CPASMethod signature, run unchanged).

Every resolved method is a :class:`SampleMethod`: it answers a dataset sample with a
:class:`Prediction` or raises :class:`PredictionFailure` with the reason.
"""

from __future__ import annotations

import importlib
import inspect
import re
import sys
from pathlib import Path

from sequences.camera import Camera
from sequences.errors import InputError

from .base import Method, Prediction
from .sample_method import FrameInputs, FrameMethod, PredictionFailure, SampleMethod, check_prediction

#: Built-in methods run here, imported only when asked for (name -> "module:Class").
BUILTINS = {
    "box": "evaluate.methods.box:BoxMethod",
    "template": "evaluate.methods.template:TemplateMethod",
}
PREDICTION_SUFFIXES = (".jsonl", ".json", ".ndjson")
_NAME = re.compile(r"^[A-Za-z0-9_.+-]+$")


def get_method(spec: str, config: dict | None = None, camera: Camera | None = None, dataset=None, base: Path | None = None) -> SampleMethod:
    """Resolve a method SPEC (see the module docstring).

    ``config`` is the method's own configuration (passed to its constructor), ``camera`` the
    dataset's camera (for cpas_toolbox classes, which take it at construction), ``dataset`` the
    dataset (the oracle reads its truth), ``base`` the folder relative predictions paths start from.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise InputError(None, f"method spec must be a non-empty string, got {spec!r}")
    spec = spec.strip()
    name, target = (part.strip() for part in spec.split("=", 1)) if "=" in spec else (None, spec)
    if name is not None and not _NAME.match(name):
        raise InputError(None, f"method name {name!r} in {spec!r} must be letters, digits, '_', '.', '+' or '-'")
    camera = camera or Camera()
    if target == "oracle":
        from .oracle import OracleMethod

        return OracleMethod(config, dataset, name or "oracle")
    if target in BUILTINS:
        return _from_class(name or target, _import(BUILTINS[target], spec), config, camera)
    if target.lower().endswith(PREDICTION_SUFFIXES) or (name is not None and ":" not in target):
        from .predictions import PredictionsFile

        if name is None:
            name = Path(target).stem
        path = Path(target)
        if base is not None and not path.is_absolute():
            path = Path(base) / path
        return PredictionsFile(name, path)
    if ":" in target:
        cls = _import(target, spec)
        return _from_class(name or cls.__name__, cls, config, camera)
    raise InputError(None, f"unknown method {spec!r}: expected {', '.join(sorted([*BUILTINS, 'oracle']))}, NAME=predictions.jsonl or NAME=module:Class")


def _load_module(module_name: str, spec: str):
    """The module, or InputError in one line when importing it fails (its own code raising anything, exits included)."""
    try:
        return importlib.import_module(module_name)
    except ImportError as error:
        raise InputError(None, f"method {spec!r} is not available: cannot import {module_name} ({error})") from error
    except (Exception, SystemExit) as error:  # the module's own code failed while importing
        raise InputError(None, " ".join(f"method {spec!r}: importing {module_name} raised {error.__class__.__name__}: {error}".split())[:400]) from error


def _import(target: str, spec: str):
    module_name, _, attribute = target.partition(":")
    if not module_name or not attribute:
        raise InputError(None, f"method {spec!r}: expected module:Class")
    try:
        module = _load_module(module_name, spec)
    except InputError as error:
        missing = isinstance(error.__cause__, ModuleNotFoundError) and error.__cause__.name == module_name.split(".")[0]
        if not missing or str(Path.cwd()) in sys.path:
            raise
        sys.path.insert(0, str(Path.cwd()))  # console scripts do not search the working folder
        module = _load_module(module_name, spec)
    try:
        cls = getattr(module, attribute)
    except AttributeError as error:
        raise InputError(None, f"method {spec!r}: module {module_name} has no {attribute}") from error
    if not inspect.isclass(cls):
        raise InputError(None, f"method {spec!r}: {attribute} is not a class")
    return cls


def is_cpas_method(cls: type) -> bool:
    """Whether ``cls`` has cpas_toolbox's CPASMethod signature (inference(color_image, depth_image, instance_mask, category_str))."""
    inference = getattr(cls, "inference", None)
    if inference is None:
        return False
    parameters = list(inspect.signature(inference).parameters)
    return parameters[1:5] == ["color_image", "depth_image", "instance_mask", "category_str"]


def _from_class(name: str, cls: type, config: dict | None, camera: Camera) -> SampleMethod:
    try:
        return _construct(name, cls, config, camera)
    except InputError:
        raise
    except (Exception, SystemExit) as error:  # a method that cannot start (missing weights, bad config) ends the run in one line
        raise InputError(None, f"method {name}: {cls.__module__}.{cls.__name__} could not be constructed ({error.__class__.__name__}: {error})"[:400]) from error


def _construct(name: str, cls: type, config: dict | None, camera: Camera) -> SampleMethod:
    if issubclass(cls, SampleMethod):
        method = cls(config)
        method.name = name
        return method
    if issubclass(cls, Method) and not is_cpas_method(cls):
        return FrameMethod(name, cls(config))
    if is_cpas_method(cls):
        from .cpas_adapter import CpasMethodAdapter

        return FrameMethod(name, CpasMethodAdapter(cls, config, camera))
    raise InputError(None, f"method {name}: {cls.__module__}.{cls.__name__} is neither an evaluate Method nor a cpas_toolbox CPASMethod")


__all__ = [
    "BUILTINS",
    "FrameInputs",
    "FrameMethod",
    "Method",
    "Prediction",
    "PredictionFailure",
    "SampleMethod",
    "check_prediction",
    "get_method",
    "is_cpas_method",
]
