"""What the benchmarks on real frames share (run_real.py, reconstruct_real.py): YCB-Video's videos in ../shared and
their objects, and the report they write (OUT/results.json and OUT/README.md)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

from sequences.errors import InputError
from sequences.ycbv import ycbv_objects


def videos_objects(shared: str | Path) -> Iterator[tuple[Path, str]]:
    """(video folder, object name) for every object of every video of ``shared``/ycbv_real, in order; InputError when
    it holds no video."""
    folder = Path(shared) / "ycbv_real"
    videos = sorted(p for p in folder.glob("[0-9]*") if p.is_dir())
    if not videos:
        raise InputError(folder, "no YCB-Video video folders here (../shared/data must lie beside the repository)")
    for root in videos:
        for name in ycbv_objects(root):  # a few objects per video
            yield root, name


def write_report(out: str | Path, rows: list[dict], text: str) -> None:
    """``rows`` as OUT/results.json and ``text`` as OUT/README.md; prints ``text``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(rows, indent=1, default=float))
    (out / "README.md").write_text(text)
    print(text)
