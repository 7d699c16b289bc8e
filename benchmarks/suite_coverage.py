"""What the suite's sequences let a reconstruction see: the generator's own coverage figures, per sequence.

    .venv/bin/python benchmarks/suite_coverage.py --split dev|heldout [--only NAME ...] [--out FILE.json]

The generator places each grasp so that the space its hand fills next to the object is seen free in frames held by
another grasp (sequences.synth.motion), but judges that against the object alone; the hand and arm of the other
grasps, and the table, can hide it too. sequences.synth.coverage measures it with every part of the scene:

- hand space free: per grasp, the share of the hand's space next to the surface that some frame where that grasp
  does not hold the object sees free (in front of the first surface along the ray). Below 1, part of the hand's place
  is never seen empty: a carving keeps it as the object, from any poses, and the box face beside it moves;
- contact seen: per grasp, the share of its contact patch that a frame held by another grasp shows unobstructed;
- never seen: the share of the whole surface that no frame shows (a deep cavity, the face lying on a table).

Read these beside the suite's truth rows (run_suite.py): a measured face off by centimetres where a grasp's hand
space is below 1 is the capture's, not the reconstruction's. The scene is drawn as the generator draws it from the
entry's seed (no image rendered); about 30 s a sequence on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.suite.spec import SHARED, SPLITS, SUITE, Entry, load_suite, resolve  # noqa: E402
from sequences.errors import run_cli  # noqa: E402


def entry_coverage(entry: Entry, frames: int, shared: Path = SHARED) -> dict:
    """The generator's coverage figures (shares 0-1, angles in degrees) of ``entry``'s scene at ``frames`` frames."""
    from sequences.camera import Camera
    from sequences.synth.coverage import measure
    from sequences.synth.generate import build_scene, object_mesh

    recipe = resolve(entry, frames, shared)
    obj = object_mesh(recipe.category, recipe.seed, recipe.mesh, recipe.mesh_axes, recipe.shape)
    scene = build_scene(obj, recipe.frames, recipe.seed, Camera(), recipe.capture)
    c = measure(obj, scene.trajectory, scene.hands, scene.layout)
    return {"sequence": entry.name, "category": entry.category, "coverage": entry.coverage, "grasps": len(c.hand_space_free),
            "hand_space_free": c.hand_space_free, "contact_seen": c.contact_seen, "surface_never_seen": c.unseen,
            "opening_deg": c.opening_deg, "bottom_deg": c.bottom_deg}


def table(rows: list[dict]) -> str:
    """A Markdown table of ``entry_coverage`` rows."""
    shares = lambda values: " ".join(f"{v:.2f}" for v in values) or "–"  # noqa: E731
    lines = ["| sequence | coverage | grasps | hand space free (per grasp) | contact seen (per grasp) | never seen |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['sequence']} | {r['coverage']} | {r['grasps']} | {shares(r['hand_space_free'])} | {shares(r['contact_seen'])} | "
              f"{r['surface_never_seen']:.0%} |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=SPLITS, required=True)
    parser.add_argument("--only", nargs="+", metavar="NAME", help="these sequences of the split only")
    parser.add_argument("--suite", default=str(SUITE), help="the suite file")
    parser.add_argument("--shared", default=str(SHARED), help="../shared/data (the real meshes and REDWOOD75's orientations)")
    parser.add_argument("--out", help="write the rows as JSON here too")
    args = parser.parse_args(argv)
    suite = load_suite(args.suite)
    try:
        entries = suite.named(args.split, args.only)
    except ValueError as error:
        parser.error(str(error))
    rows = []
    for k, entry in enumerate(entries, start=1):
        rows.append(entry_coverage(entry, suite.frames, Path(args.shared)))
        print(f"[{k}/{len(entries)}] {entry.name}: hand space free {' '.join(f'{v:.2f}' for v in rows[-1]['hand_space_free'])}", flush=True)
    print()
    print(table(rows))
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        partial = out.with_name(out.name + ".partial")
        partial.write_text(json.dumps({"split": args.split, "frames": suite.frames, "rows": rows}, indent=1))
        partial.replace(out)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
