"""The benchmark suite's specification (``benchmarks/suite.yaml``): its sequences, their splits, and how each is made.

A sequence entry names a shape source, a coverage, a texture, a sensor and a seed (see the YAML's header);
:func:`load_suite` checks every entry, :func:`resolve` turns one into ``sequences.synth.generate_sequence``'s
arguments (the real meshes lie in ``../shared/data``), and :func:`build` generates it once into a cache
folder named by the entry and everything that makes it (a changed entry or generator makes a new folder).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from sequences.annotation import CATEGORIES
from sequences.documents import load_document
from sequences.errors import InputError
from sequences.synth.options import COVERAGES, GENERATOR_VERSION, PROCEDURAL_SHAPES, TEXTURES, CaptureOptions, SensorOptions

REPO = Path(__file__).resolve().parents[2]
SUITE = REPO / "benchmarks" / "suite.yaml"
SHARED = REPO.parent / "shared" / "data"
SPLITS = ("dev", "heldout")
ENTRY_KEYS = {"name", "split", "category", "shape", "coverage", "keys", "turn_speed", "texture", "seed", "sensor", "frames"}


@dataclass(frozen=True)
class Setting:
    """How the boxes of a tracked setting are placed: how many, and how far off at most (degrees, metres, extents share)."""

    name: str
    boxes: int
    degrees: float
    metres: float
    extents: float


@dataclass(frozen=True)
class Entry:
    """One sequence of the suite, as the YAML names it."""

    name: str
    split: str
    category: str
    shape: str
    coverage: str = "every_side"
    keys: str | None = None
    turn_speed: float = 1.0
    texture: str = "pattern"
    seed: int = 0
    sensor: str = "redwood"


@dataclass
class Suite:
    entries: list[Entry]
    settings: list[Setting]
    frames: int
    quick_frames: int
    quick: dict[str, list[str]] = field(default_factory=dict)

    def split(self, name: str, quick: bool = False) -> list[Entry]:
        """The entries of split ``name`` (its quick subset with ``quick``), in the file's order."""
        chosen = [e for e in self.entries if e.split == name]
        if quick:
            wanted = set(self.quick.get(name, []))
            chosen = [e for e in chosen if e.name in wanted]
        return chosen

    def named(self, split: str, names: list[str] | None, quick: bool = False) -> list[Entry]:
        """The entries of :meth:`split` whose name is in ``names`` (all of them for None); ValueError names those not
        in it."""
        entries = self.split(split, quick)
        if not names:
            return entries
        unknown = sorted(set(names) - {e.name for e in entries})
        if unknown:
            raise ValueError(f"not in the {split} split{' quick subset' if quick else ''}: {', '.join(unknown)}")
        return [e for e in entries if e.name in names]


def _entry(path: Path, raw) -> Entry:
    if not isinstance(raw, dict) or not {"name", "split", "category", "shape", "seed"} <= set(raw):
        raise InputError(path, f"a sequence needs name, split, category, shape and seed, got {raw!r}")
    unknown = sorted(set(raw) - ENTRY_KEYS)
    if unknown:
        raise InputError(path, f"sequence {raw['name']!r}: unknown keys {unknown}")
    entry = Entry(**{k: v for k, v in raw.items() if k != "frames"})
    where = f"sequence {entry.name!r}"
    if entry.split not in SPLITS:
        raise InputError(path, f"{where}: split must be one of {SPLITS}")
    if entry.category not in CATEGORIES:
        raise InputError(path, f"{where}: category {entry.category!r} is not one of {', '.join(CATEGORIES)}")
    source, _, name = entry.shape.partition(":")
    if source not in ("procedural", "redwood75", "nocs", "ycb") or not name:
        raise InputError(path, f"{where}: shape must be procedural:<shape>, redwood75:<id>, nocs:<split>/<model> or ycb:<object>")
    if source == "procedural" and PROCEDURAL_SHAPES.get(name) != entry.category:
        raise InputError(path, f"{where}: procedural shape {name!r} is not a {entry.category}")
    if entry.coverage not in COVERAGES or entry.texture not in TEXTURES or entry.sensor not in ("redwood", "ideal"):
        raise InputError(path, f"{where}: coverage, texture or sensor not one of {COVERAGES}, {TEXTURES}, (redwood, ideal)")
    if (entry.keys is not None) != (entry.coverage == "key_orientations"):
        raise InputError(path, f"{where}: key_orientations needs keys (redwood75:<id> or drawn), other coverages none")
    if entry.keys not in (None, "drawn") and not entry.keys.startswith("redwood75:"):
        raise InputError(path, f"{where}: keys must be redwood75:<id> or drawn")
    return entry


def load_suite(path: str | Path = SUITE) -> Suite:
    """Read and check the suite file: unique names, known splits, no real mesh and no seed in both splits."""
    path = Path(path)
    data = load_document(path, "suite file", as_yaml=True)
    if not isinstance(data, dict) or not isinstance(data.get("sequences"), list):
        raise InputError(path, "the suite must be a mapping with a list of sequences")
    entries = [_entry(path, raw) for raw in data["sequences"]]
    names = [e.name for e in entries]
    if len(set(names)) != len(names):
        raise InputError(path, "sequence names must be unique")
    # a procedural shape is drawn from the seed: another seed, another shape; a real mesh is one shape
    for attribute, counted in (("seed", lambda e: True), ("shape", lambda e: not e.shape.startswith("procedural:"))):
        dev = {getattr(e, attribute) for e in entries if e.split == "dev" and counted(e)}
        held = {getattr(e, attribute) for e in entries if e.split == "heldout" and counted(e)}
        if dev & held:
            raise InputError(path, f"the held-out split must not share a {attribute} with dev: {sorted(dev & held)}")
    settings = [Setting(name, **values) for name, values in (data.get("settings") or {}).items()]
    quick = data.get("quick") or {}
    for split, listed in quick.items():
        missing = sorted(set(listed) - {e.name for e in entries if e.split == split})
        if missing:
            raise InputError(path, f"quick {split}: no such {split} sequences {missing}")
    return Suite(entries, settings, int(data.get("frames", 100)), int(data.get("quick_frames", 50)), quick)


@dataclass(frozen=True)
class Recipe:
    """``generate_sequence``'s arguments for an entry."""

    category: str
    frames: int
    seed: int
    mesh: str | None
    mesh_axes: str
    shape: str | None
    capture: CaptureOptions

    def key(self) -> str:
        """A short hash of everything that makes the sequence (and the generator's version)."""
        text = json.dumps({**self.__dict__, "capture": self.capture.to_dict(), "generator": GENERATOR_VERSION}, sort_keys=True, default=str)
        return hashlib.sha1(text.encode()).hexdigest()[:10]


def resolve(entry: Entry, frames: int, shared: Path = SHARED) -> Recipe:
    """The generator's arguments for ``entry`` at ``frames`` frames; InputError names a real mesh that is missing."""
    source, _, name = entry.shape.partition(":")
    mesh, axes, shape = None, "shapenet", None
    if source == "procedural":
        shape = name
    elif source == "redwood75":
        mesh, axes = shared / "redwood75" / "meshes" / f"{name}.obj", "redwood75"
    elif source == "nocs":
        mesh, axes = shared / "nocs_real_sample" / "obj_models" / f"{name}_norm.obj", "nocs"
    else:
        folder = shared / "ycbv_real" / "models" / name
        mesh, axes = (folder / "model.obj" if (folder / "model.obj").is_file() else folder / "points.xyz"), "ycb"
    if mesh is not None and not mesh.is_file():
        raise InputError(mesh, f"sequence {entry.name}: the real mesh is missing (../shared/data must lie beside the repository)")
    keys = None
    if entry.keys is not None and entry.keys != "drawn":
        keys = f"{shared / 'redwood75' / 'annotations.json'}:{entry.keys.partition(':')[2]}"
    sensor = SensorOptions.ideal() if entry.sensor == "ideal" else SensorOptions()
    capture = CaptureOptions(coverage=entry.coverage, keys=keys, turn_speed=float(entry.turn_speed), texture=entry.texture, sensor=sensor)
    return Recipe(entry.category, frames, int(entry.seed), None if mesh is None else str(mesh), axes, shape, capture)


def build(entry: Entry, frames: int, data: Path, shared: Path = SHARED) -> Path:
    """The entry's sequence folder in the cache ``data``, generated on first use."""
    from sequences.synth import generate_sequence

    recipe = resolve(entry, frames, shared)
    root = Path(data) / f"{entry.name}-{frames}f-{recipe.key()}"
    if not (root / "truth" / "truth.json").is_file():
        generate_sequence(root, recipe.category, recipe.frames, recipe.seed, recipe.mesh, recipe.mesh_axes, shape=recipe.shape, capture=recipe.capture)
    return root
