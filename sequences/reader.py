"""Reading Redwood-layout RGB-D sequences: ``SEQ/rgb/*.jpg|png``, ``SEQ/depth/*.png``, optional ``SEQ/camera.yaml``.

Redwood names files ``<frame number, 7 digits>-<timestamp in microseconds, 12 digits>``; colour
and depth are numbered separately and are paired by nearest timestamp within a tolerance. Names
without timestamps pair by sorted order. A frame's id is its colour file's frame number (or the
colour file's stem). Opening a sequence lists files only; images are read on demand.
"""

from __future__ import annotations

import os
import re
import threading
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import Camera
from .errors import InputError
from .images import read_color, read_depth_raw
from .names import safe_name

COLOR_SUFFIXES = (".jpg", ".jpeg", ".png")
DEPTH_SUFFIXES = (".png",)
REDWOOD_NAME = re.compile(r"^(\d+)-(\d+)$")
#: Median measured depth (metres) a hand-held capture's frames can have.
PLAUSIBLE_DEPTH = (0.1, 10.0)
#: Default pairing tolerance: half a frame period of a 30 Hz sensor, microseconds.
DEFAULT_PAIRING_TOLERANCE_US = 16_667
#: Decoded depth frames a sequence keeps for the next read, at most (bytes; 256 MB, about 400 VGA frames): `check`
#: decodes every frame before the work starts, and the work reads them again (the tracker; reconstruction's carving,
#: fusion and labelling, one pass each). The first frames read are kept, not the last: a pass front to back over a
#: longer sequence then still finds those. Per Sequence object, in each process (a forked worker holds its own copy).
DEPTH_CACHE_BYTES = 256 * 2**20
#: Every open sequence, for a forked child to make its locks anew (a thread of the parent may hold one at the fork).
_OPEN: "weakref.WeakSet[Sequence]" = weakref.WeakSet()


def _new_locks_after_fork() -> None:
    for sequence in list(_OPEN):
        sequence._decoded_lock = threading.Lock()


os.register_at_fork(after_in_child=_new_locks_after_fork)


@dataclass(frozen=True)
class FrameFiles:
    """One paired frame: its id and the colour and depth files (timestamps in microseconds, or None)."""

    id: str
    color_path: Path
    depth_path: Path
    color_time_us: int | None = None
    depth_time_us: int | None = None


@dataclass
class Pairing:
    """The result of pairing colour and depth files."""

    frames: list[FrameFiles]
    unpaired_color: list[Path] = field(default_factory=list)
    unpaired_depth: list[Path] = field(default_factory=list)


def parse_redwood_name(path: Path) -> tuple[int, int] | None:
    """(frame number, timestamp in microseconds) of a Redwood file name, or None."""
    match = REDWOOD_NAME.match(path.stem)
    return (int(match.group(1)), int(match.group(2))) if match else None


def pair_frames(color: list[Path], depth: list[Path], tolerance_us: int = DEFAULT_PAIRING_TOLERANCE_US) -> Pairing:
    """Pair colour and depth files by nearest timestamp (Redwood names) or by sorted order.

    Each depth file serves at most one colour file (the nearest in time); colour files with no
    depth within ``tolerance_us`` and depth files left over are reported as unpaired.
    """
    color = sorted(color)
    depth = sorted(depth)
    color_names = [parse_redwood_name(p) for p in color]
    depth_names = [parse_redwood_name(p) for p in depth]
    timed = color and depth and all(color_names) and all(depth_names)
    if not timed:
        n = min(len(color), len(depth))
        frames = [FrameFiles(c.stem, c, d) for c, d in zip(color[:n], depth[:n])]
        return Pairing(frames, color[n:], depth[n:])

    color_order = np.argsort([t for _, t in color_names], kind="stable")
    color = [color[i] for i in color_order]
    color_names = [color_names[i] for i in color_order]
    depth_order = np.argsort([t for _, t in depth_names], kind="stable")
    depth = [depth[i] for i in depth_order]
    depth_names = [depth_names[i] for i in depth_order]
    tc = np.array([t for _, t in color_names], dtype=np.int64)
    td = np.array([t for _, t in depth_names], dtype=np.int64)
    # nearest depth for each colour frame
    right = np.clip(np.searchsorted(td, tc), 0, len(td) - 1)
    left = np.clip(right - 1, 0, len(td) - 1)
    take_left = np.abs(td[left] - tc) <= np.abs(td[right] - tc)
    nearest = np.where(take_left, left, right)
    gap = np.abs(td[nearest] - tc)
    ok = gap <= tolerance_us
    # a depth frame claimed twice goes to the closer colour frame
    order = np.lexsort((gap, nearest))
    claimed = np.zeros(len(td), dtype=bool)
    keep = np.zeros(len(tc), dtype=bool)
    for i in order[ok[order]]:  # loop over frames (not pixels): a few thousand at most
        if not claimed[nearest[i]]:
            claimed[nearest[i]] = True
            keep[i] = True
    frames = []
    for i in np.flatnonzero(keep):
        c, d = color[i], depth[nearest[i]]
        frames.append(FrameFiles(c.stem.split("-")[0], c, d, int(tc[i]), int(td[nearest[i]])))
    unpaired_color = [color[i] for i in np.flatnonzero(~keep)]
    unpaired_depth = [depth[j] for j in np.flatnonzero(~claimed)]
    return Pairing(frames, unpaired_color, unpaired_depth)


def _list_images(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes and not p.name.startswith("."))


class Sequence:
    """An RGB-D sequence, read lazily: Redwood's layout (``SEQ/rgb``, ``SEQ/depth``), or another layout that
    :func:`open_sequence` recognises (YCB-Video's, BOP's), whose frames and camera its reader lists.

    ``frames`` lists the paired frames in time order; ``color(i)`` gives (H, W, 3) uint8 RGB and
    ``depth(i)`` gives (H, W) float32 metres with 0 where there is no measurement. ``layout`` names the
    layout ("redwood", "ycbv", "bop").
    """

    def __init__(self, root: str | Path, tolerance_us: int = DEFAULT_PAIRING_TOLERANCE_US) -> None:
        root = Path(root)
        if not root.exists():
            raise InputError(root, "sequence folder does not exist")
        if not root.is_dir():
            raise InputError(root, "not a folder (a sequence is a folder with rgb/ and depth/)")
        for sub in ("rgb", "depth"):
            if not (root / sub).is_dir():
                raise InputError(root / sub, f"missing {sub}/ folder (Redwood layout: SEQ/rgb and SEQ/depth)")
        camera_file = root / "camera.yaml"
        camera = Camera.from_yaml(camera_file) if camera_file.exists() else Camera()
        color = _list_images(root / "rgb", COLOR_SUFFIXES)
        depth = _list_images(root / "depth", DEPTH_SUFFIXES)
        if not color:
            raise InputError(root / "rgb", "no colour images (*.jpg, *.png)")
        if not depth:
            raise InputError(root / "depth", "no depth images (*.png)")
        pairing = pair_frames(color, depth, tolerance_us)
        if not pairing.frames:
            raise InputError(root, f"no colour frame has a depth frame within {tolerance_us} us")
        self._setup(root, pairing.frames, camera, "redwood", pairing.unpaired_color, pairing.unpaired_depth)

    def _setup(self, root: Path, frames: list[FrameFiles], camera: Camera, layout: str,
               unpaired_color: list[Path] | None = None, unpaired_depth: list[Path] | None = None) -> None:
        self.root = root
        self.name = safe_name(root.resolve().name)  # file names are built from it: a plain name
        self.camera = camera
        self.layout = layout
        self.frames: list[FrameFiles] = frames
        self.unpaired_color = unpaired_color or []
        self.unpaired_depth = unpaired_depth or []
        self._index = {f.id: i for i, f in enumerate(self.frames)}
        if len(self._index) != len(self.frames):
            raise InputError(root, "two colour files share a frame number")
        self._new_cache()

    def _new_cache(self) -> None:
        self._decoded: dict[Path, np.ndarray] = {}  # depth path -> read-only image
        self._decoded_bytes = 0
        self._decoded_lock = threading.Lock()  # frames are read on helper threads too (check, decoding ahead)
        _OPEN.add(self)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        del state["_decoded"], state["_decoded_bytes"], state["_decoded_lock"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._new_cache()

    @classmethod
    def from_frames(cls, root: str | Path, frames: list[FrameFiles], camera: Camera, layout: str) -> "Sequence":
        """A sequence of already paired ``frames`` (another layout's reader lists them)."""
        sequence = cls.__new__(cls)
        sequence._setup(Path(root), frames, camera, layout)
        return sequence

    def __len__(self) -> int:
        return len(self.frames)

    def __repr__(self) -> str:
        return f"Sequence({str(self.root)!r}, frames={len(self)})"

    @property
    def ids(self) -> list[str]:
        return [f.id for f in self.frames]

    def index(self, frame_id: str) -> int:
        """Position of a frame id in ``frames``."""
        try:
            return self._index[str(frame_id)]
        except KeyError:
            raise KeyError(f"frame {frame_id!r} is not in {self.root}") from None

    def _resolve(self, frame: int | str) -> FrameFiles:
        return self.frames[frame if isinstance(frame, (int, np.integer)) else self.index(frame)]

    def color(self, frame: int | str) -> np.ndarray:
        """Colour image (H, W, 3) uint8 RGB of a frame (index or id)."""
        return read_color(self._resolve(frame).color_path, self.camera)

    def depth_raw(self, frame: int | str) -> np.ndarray:
        """Depth image (H, W) uint16 in sensor units (multiply by ``camera.depth_scale`` for metres), read-only: decoded
        frames are kept for the next read up to DEPTH_CACHE_BYTES."""
        path = self._resolve(frame).depth_path
        with self._decoded_lock:
            if path in self._decoded:
                return self._decoded[path]
        array = read_depth_raw(path, self.camera)
        if not array.any():
            raise InputError(path, "depth frame has no valid pixel (all zero)")
        array.flags.writeable = False
        with self._decoded_lock:
            if path not in self._decoded and self._decoded_bytes + array.nbytes <= DEPTH_CACHE_BYTES:
                self._decoded[path] = array
                self._decoded_bytes += array.nbytes
        return array

    def depth(self, frame: int | str) -> np.ndarray:
        """Depth image (H, W) float32 in metres, 0 = no measurement."""
        return self.depth_raw(frame).astype(np.float32) * np.float32(self.camera.depth_scale)

    def check(self) -> None:
        """Read every frame once (raises InputError on the first bad one), then :meth:`check_depth_scale`."""
        for i in range(len(self)):
            self.color(i)
            self.depth_raw(i)
        self.check_depth_scale()

    def check_depth_scale(self, samples: int = 3) -> None:
        """Raise InputError unless the measured depth (metres) of a few frames lies mostly within PLAUSIBLE_DEPTH: a
        depth scale ten times off puts a hand-held object 6 m or 6 cm away."""
        picks = np.unique(np.linspace(0, len(self) - 1, min(samples, len(self))).round().astype(int))
        depth = np.concatenate([self.depth(int(i)).reshape(-1) for i in picks])
        median = float(np.median(depth[depth > 0]))
        if not PLAUSIBLE_DEPTH[0] <= median <= PLAUSIBLE_DEPTH[1]:
            source = self.root / "camera.yaml" if (self.root / "camera.yaml").exists() else self.frames[0].depth_path.parent
            raise InputError(source, f"the measured depth is {median:.3g} m at the median, outside {PLAUSIBLE_DEPTH[0]}-{PLAUSIBLE_DEPTH[1]} m: "
                                     f"is the depth scale ({self.camera.depth_scale:g} m per unit) right?")


def open_sequence(root: str | Path, tolerance_us: int = DEFAULT_PAIRING_TOLERANCE_US) -> Sequence:
    """Open a sequence (lists files only; see :class:`Sequence`): Redwood's layout, a BOP scene (``rgb/``, ``depth/``
    and ``scene_camera.json``) or a YCB-Video video folder (``NNNNNN-color.*``, ``NNNNNN-depth.png``, ``poses.json``)."""
    root = Path(root)
    if root.is_dir() and (root / "scene_camera.json").is_file():
        from .bop import open_bop_scene

        return open_bop_scene(root)
    if root.is_dir() and not (root / "rgb").exists() and any(root.glob("*-color.*")):
        from .ycbv import open_ycbv_video

        return open_ycbv_video(root)
    return Sequence(root, tolerance_us)
