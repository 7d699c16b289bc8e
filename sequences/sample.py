"""The bundled sample sequence: a synthetic mug, generated deterministically on first use and cached.

``annotate`` opens it when no sequence is given. It lives in ``$REDWOOD_GT_CACHE`` (or
``~/.cache/redwood-gt``) as ``sample-mug-v<generator version>/``, with its truth in ``truth/`` and no annotation
document (an annotator starts from scratch). Generation goes to a private temporary folder that
is renamed into place, so two processes racing to create it both end up with one complete copy.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from .synth.options import GENERATOR_VERSION

SAMPLE_NAME = f"sample-mug-v{GENERATOR_VERSION}"
SAMPLE_CATEGORY = "mug"
SAMPLE_FRAMES = 60
SAMPLE_SEED = 7


def cache_dir() -> Path:
    """``$REDWOOD_GT_CACHE``, else ``~/.cache/redwood-gt``."""
    env = os.environ.get("REDWOOD_GT_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "redwood-gt"


def _complete(path: Path) -> bool:
    return (path / "truth" / "truth.json").is_file() and (path / "rgb").is_dir() and (path / "depth").is_dir()


def sample_sequence() -> Path:
    """The sample sequence's folder (a {frames}-frame mug), generated on first use into the cache."""
    from .synth import generate_sequence

    final = cache_dir() / SAMPLE_NAME
    if _complete(final):
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{SAMPLE_NAME}.", dir=final.parent))
    try:
        generated = generate_sequence(work / SAMPLE_NAME, SAMPLE_CATEGORY, frames=SAMPLE_FRAMES, seed=SAMPLE_SEED)
        if final.exists() and not _complete(final):
            # a leftover from an interrupted run of an older version: replace it (never a user's data: it is our cache)
            shutil.rmtree(final, ignore_errors=True)
        try:
            os.rename(generated, final)
        except OSError:
            if not _complete(final):  # not a lost race: a real problem
                raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return final


sample_sequence.__doc__ = sample_sequence.__doc__.format(frames=SAMPLE_FRAMES)
