"""``evaluate`` as a batch: the methods that run here, one unit per method and chunk of samples (see :mod:`batch`).

A method run here on the frames (``box``, ``template``, ``NAME=module:Class``) costs up to seconds a sample;
predictions files and the oracle are look-ups, and run in the client as before. A unit opens the dataset,
builds its method and predicts its chunk (``CHUNK`` samples in the dataset's order, whatever the worker count),
then writes the predictions to ``OUT/.batch/<method>/<first>-<last>.npz`` atomically; the client loads every
chunk and scores them all at once, as without a batch (:func:`evaluate.runner.evaluate_dataset`), so the
results are the same for any worker count and engine.

What the samples of a method share (the template method's templates) is kept in ``OUT/.batch/shared/<method>/``
(:meth:`evaluate.methods.base.Method.prepare_shared`): the first unit that needs it builds it and writes it
atomically, the units that start later read it. Units that start together each build it: the client does not
build it for them first, as every unit would then wait for it (the client imports the method's libraries
itself, while the units' processes have them preloaded).

Finished (:mod:`batch.units`): the chunk's marker (``.json`` beside it) records the state of its inputs and
output (:func:`chunk_state`): the method's spec and configuration with the files it names, the source file of its
class's module (an edited method runs again; a change in a module it imports does not count: ``--redo``), the
options that shape a prediction (the surface samples and their seed), per sample its truth (pose, box, category,
symmetry, a mug's handle), camera, the contents of its mask and mesh files and the names, sizes and times of its
frames, and the predictions file itself.
"""

from __future__ import annotations

import hashlib
import io
import json
import sys
from pathlib import Path

import numpy as np

from batch import Unit
from batch.units import file_bytes, listing, sha256_text
from evaluate import PRELOAD
from evaluate.config import EvaluateConfig
from sequences.atomic import write_bytes_atomic
from sequences.errors import InputError
from sequences.names import safe_name

#: Samples per unit: a dozen seconds of the template method, a fraction of one for the box; fixed, so that a rerun
#: with another worker count finds the same units finished.
CHUNK = 16
#: Where the units' predictions and markers live in OUT.
MARKERS = ".batch"


def _file(path: Path | None) -> list | None:
    """A frame file by its name, size and modification time (frames are large; replacing one changes these)."""
    if path is None:
        return None
    try:
        info = Path(path).stat()
    except OSError:
        return [str(path), None, None]
    return [str(path), info.st_size, info.st_mtime_ns]


def _content(path: Path | None, digests: dict) -> list | None:
    """A truth file (a mesh, a mask: small) by its name and content's SHA-256, read once per ``digests``."""
    if path is None:
        return None
    if path not in digests:
        try:
            digests[path] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        except OSError:
            digests[path] = None
    return [str(path), digests[path]]


def sample_state(sample, digests: dict | None = None) -> list:
    """What a prediction for ``sample`` may depend on: its truth (pose, box, category, symmetry, a mug's handle; the
    mesh and mask files' contents: a mask may be rendered from the mesh), its camera and its frame files."""
    digests = {} if digests is None else digests
    return [sample.dataset, sample.sequence, sample.frame, sample.instance, sample.category, sample.symmetry, sample.position.tolist(),
            sample.orientation.tolist(), sample.extents.tolist(), sample.handle_visible, sample.camera.to_dict(), _file(sample.color_path),
            _file(sample.depth_path), _content(sample.mask_path, digests), _content(sample.mesh_path, digests)]


def referenced_files(value, base: Path | None, digests: dict) -> list:
    """The files and folders a method's configuration names (a template folder, a model's weights): a file by its
    content, a folder by its files' names, sizes and times; strings that name nothing are left out."""
    if isinstance(value, dict):
        return [[str(k), referenced_files(v, base, digests)] for k, v in sorted(value.items(), key=lambda item: str(item[0]))]
    if isinstance(value, (list, tuple)):
        return [referenced_files(v, base, digests) for v in value]
    if not isinstance(value, (str, Path)) or not str(value) or "\n" in str(value):
        return []
    path = Path(value) if Path(value).is_absolute() or base is None else Path(base) / value
    try:
        if path.is_file():
            return _content(path, digests)
        if path.is_dir():
            return [str(path), listing(path, ("",))]
    except OSError:  # a name too long for a path, ...
        pass
    return []


def method_source(method) -> bytes:
    """The source file of the module that defines the method's class (b"" where there is none)."""
    target = getattr(method, "method", method)
    module = sys.modules.get(type(target).__module__)
    path = getattr(module, "__file__", None)
    try:
        return Path(path).read_bytes() if path else b""
    except OSError:
        return b""


def chunk_state(config: EvaluateConfig, entry, method, samples: list, predictions: bytes) -> str:
    """A chunk's state (its marker records it): the method (spec, configuration and the files it names, its class's
    source), the options that shape a prediction (the surface samples and their seed), every sample's truth and
    files (:func:`sample_state`), and the predictions file written (a chunk file replaced or cut runs again)."""
    digests: dict = {}
    return sha256_text("evaluate", entry.spec, entry.config, None if entry.base is None else str(entry.base),
                       referenced_files(entry.config, entry.base, digests), method_source(method), config.surface_samples, config.seed,
                       [sample_state(s, digests) for s in samples], hashlib.sha256(predictions).hexdigest())


#: The dataset and methods of the last chunk this process predicted, by their configuration: chunks predicted in
#: one process (``--workers 1``) build a method (a model loaded, templates prepared) once.
_opened: dict = {}


def _key(config: EvaluateConfig) -> str:
    return sha256_text(str(config.dataset), str(config.frames), [(m.spec, m.config, str(m.base)) for m in config.methods])


def _open(config: EvaluateConfig):
    """(dataset, methods) of ``config``, kept for the next chunk of this process."""
    from evaluate.datasets import open_dataset
    from evaluate.runner import resolve_methods

    key = _key(config)
    if key not in _opened:
        _opened.clear()
        dataset = open_dataset(config.dataset, config.frames)
        _opened[key] = (dataset, resolve_methods(config, dataset))
    return _opened[key]


def shared_folder(config: EvaluateConfig, name: str) -> Path:
    """Where method ``name`` keeps what its samples share for this batch (its templates, ...)."""
    return Path(config.out) / MARKERS / "shared" / safe_name(name, fallback="method")


def categories_of(samples: list) -> list[str]:
    """The samples' categories, each once, in their order."""
    return list(dict.fromkeys(s.category for s in samples))


def _prepare(method, samples: list, folder: Path) -> None:
    """The method's :meth:`~evaluate.methods.base.Method.prepare_shared` for ``samples``' categories; a failure there
    is left to the samples (predicting them says why, one by one, as without a batch)."""
    if samples:
        try:
            method.prepare_shared(categories_of(samples), folder)
        except Exception:
            pass


def predict_chunk(config: EvaluateConfig, index: int, first: int, last: int, path: str) -> dict:
    """A unit, on a worker: method ``index`` of ``config`` on samples ``first``..``last`` (inclusive); writes them to
    ``path`` (npz) and returns the summary (with the state its marker records)."""
    from evaluate.methods import FrameInputs
    from evaluate.runner import predict_sample

    dataset, methods = _open(config)
    if last >= len(dataset):
        raise InputError(config.dataset, f"the dataset has {len(dataset)} samples, not {last + 1}: it changed during the run")
    method = methods[index]
    samples = dataset.samples[first:last + 1]
    _prepare(method, samples, shared_folder(config, method.name))  # what another unit prepared (templates): read, not rebuilt
    results = [predict_sample(method, sample, FrameInputs(dataset, sample), config) for sample in samples]
    data = chunk_bytes(results)
    write_bytes_atomic(path, data)
    return {"method": method.name, "samples": len(samples), "failed": sum(p is None for p, _ in results),
            "state": chunk_state(config, config.methods[index], method, samples, data)}


def chunk_bytes(results: list[tuple]) -> bytes:
    """A chunk's predictions as an npz: arrays per field, the points concatenated with their offsets, and the
    reasons, scores and categories as JSON (no pickles: a file in OUT is data, never code)."""
    n = len(results)
    ok = np.array([p is not None for p, _ in results], dtype=bool)
    position, orientation, extents = np.zeros((n, 3)), np.zeros((n, 4)), np.zeros((n, 3))
    counts = np.full(n, -1, dtype=np.int64)  # -1: no points
    points = []
    meta = {"reasons": [r for _, r in results], "scores": [], "categories": []}
    for i, (p, _) in enumerate(results):
        if p is None:
            meta["scores"].append(None)
            meta["categories"].append(None)
            continue
        position[i], orientation[i], extents[i] = p[0], p[1], p[2]
        if p[3] is not None:
            counts[i] = len(p[3])
            points.append(np.asarray(p[3], dtype=np.float64).reshape(-1, 3))
        meta["scores"].append(float(p[4]))
        meta["categories"].append(p[5])
    buffer = io.BytesIO()
    np.savez(buffer, ok=ok, position=position, orientation=orientation, extents=extents, counts=counts,
             points=np.concatenate(points) if points else np.zeros((0, 3)), meta=np.array(json.dumps(meta)))
    return buffer.getvalue()


def load_chunk(path: Path) -> list[tuple]:
    """The (prediction or None, reason or None) pairs of a chunk file (:func:`chunk_bytes`)."""
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
        ok, counts, points = data["ok"], data["counts"], data["points"]
        position, orientation, extents = data["position"], data["orientation"], data["extents"]
        starts = np.concatenate([[0], np.cumsum(np.maximum(counts, 0))])
        out = []
        for i in range(len(ok)):
            if not ok[i]:
                out.append((None, meta["reasons"][i]))
                continue
            cloud = points[starts[i]:starts[i + 1]] if counts[i] >= 0 else None
            out.append(((position[i], orientation[i], extents[i], cloud, meta["scores"][i], meta["categories"][i]), meta["reasons"][i]))
    return out


def plan(config: EvaluateConfig, dataset, methods: list) -> list[tuple[Unit, int, int, int, Path]]:
    """The units of the methods that run here: (unit, method index, first, last, predictions file)."""
    folder = Path(config.out) / MARKERS
    planned = []
    for index, method in enumerate(methods):
        if not method.needs_frames:
            continue
        entry = config.methods[index]
        name = safe_name(method.name, fallback=f"method{index}")
        for first in range(0, len(dataset), CHUNK):
            last = min(first + CHUNK, len(dataset)) - 1
            path = folder / name / f"{first:05d}-{last:05d}.npz"
            samples = dataset.samples[first:last + 1]

            def state(entry=entry, method=method, samples=samples, path=path) -> str | None:
                data = file_bytes(path)
                return None if data is None else chunk_state(config, entry, method, samples, data)

            unit = Unit(f"{method.name} {first + 1}-{last + 1}", predict_chunk, (config, index, first, last, str(path)),
                        path.with_suffix(".json"), state, size=last - first + 1)
            planned.append((unit, index, first, last, path))
    return planned


def batch_predictor(config: EvaluateConfig, workers: int, cluster: str | None, redo: bool, quiet: bool, report: dict):
    """A ``predict`` for :func:`evaluate.runner.evaluate_dataset`: the methods run here as a batch, the others in
    this process (a bar over all predictions); the batch's report goes into ``report``."""

    def predict(dataset, methods, predicted, reasons) -> None:
        from batch import run_batch
        from evaluate.methods import FrameInputs
        from evaluate.runner import predict_sample

        planned = plan(config, dataset, methods)
        _opened.clear()
        _opened[_key(config)] = (dataset, methods)  # chunks run in this process (one worker) use these, opened once
        batch = run_batch([p[0] for p in planned], workers=workers, cluster=cluster, redo=redo, desc="evaluate", noun="prediction",
                          quiet=quiet, preload=PRELOAD, inline=True, describe=lambda o: f"{o.key}: {o.summary.get('samples', '?')} predictions in {o.seconds:.1f} s")
        for (unit, index, first, last, path), outcome in zip(planned, batch.outcomes):
            name = methods[index].name
            if outcome.status == "failed":
                for i in range(first, last + 1):
                    reasons[name][i] = f"its unit failed: {outcome.error}"[:300]
                continue
            for i, (prediction, reason) in enumerate(load_chunk(path), start=first):
                predicted[name][i], reasons[name][i] = prediction, reason
        report.update(batch.as_dict())
        here = [m for m in methods if not m.needs_frames]
        if here:  # look-ups: in this process, as without a batch
            from batch.runner import progress_bar

            bar = progress_bar(len(dataset) * len(here), "evaluate (look-ups)", "prediction", quiet)
            for i, sample in enumerate(dataset):
                inputs = FrameInputs(dataset, sample)
                for method in here:
                    predicted[method.name][i], reasons[method.name][i] = predict_sample(method, sample, inputs, config)
                    bar.update(1)
            bar.close()

    return predict
