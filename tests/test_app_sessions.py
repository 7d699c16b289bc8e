"""Sessions (issue 49, item 8): each tab says how many others share the session; an empty or cut-short document is
refused in one line, never read as a shorter one; old documents still load; written files keep the umask."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest
import viser
import websockets.sync.client
from test_app_fixtures import make_sequence

from annotate.app import App
from annotate.app_state import AppState
from sequences.annotation import END_MARKER, FIRST_LINE, load_annotation
from sequences.errors import InputError
from sequences.reader import open_sequence

OLD_DOCUMENT = """\
sequence: box_seq
category: mug
symmetry: none
extents: [0.08, 0.12, 0.06]
frames:
  '0000001': {position: [0.0, 0.0, 0.7], orientation: [0.0, 0.0, 0.0, 1.0], source: manual}
  '0000002': {position: [0.0, 0.0, 0.71], orientation: [0.0, 0.0, 0.0, 1.0], source: tracked, fitness: 0.9}
"""


@pytest.fixture(scope="module")
def sequence_root(tmp_path_factory):
    root, _ = make_sequence(tmp_path_factory.mktemp("sessions") / "box_seq", frames=4)
    return root


@pytest.fixture
def seq(sequence_root, tmp_path):
    root = tmp_path / "box_seq"
    shutil.copytree(sequence_root, root)
    return open_sequence(root)


def _wait(condition, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


def _tab(url: str):
    """A websocket client that viser counts as a tab: it reports its camera, as the page does once it has one."""
    import msgspec

    tab = websockets.sync.client.connect(url, subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10, max_size=None)
    camera = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, 0.0], "fov": 1.0, "near": 0.01,
              "far": 100.0, "image_height": 480, "image_width": 640, "look_at": [0.0, 0.0, 1.0], "up_direction": [0.0, -1.0, 0.0]}
    tab.send(msgspec.msgpack.encode(camera))
    return tab


def test_each_tab_says_how_many_others_share_the_session(seq):
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = App(server, seq)
    url = f"ws://127.0.0.1:{server.get_port()}"
    try:
        first = _tab(url)
        assert _wait(lambda: len(app._clients) == 1) and app.tabs.content == ""
        second = _tab(url)
        third = _tab(url)
        assert _wait(lambda: "2 other tabs" in app.tabs.content), app.tabs.content
        assert "share the document" in app.tabs.content
        third.close()
        assert _wait(lambda: "1 other tab**" in app.tabs.content), app.tabs.content
        second.close()
        first.close()
        assert _wait(lambda: app.tabs.content == ""), app.tabs.content
    finally:
        app.close()
        server.stop()


def test_written_documents_are_whole_or_refused_at_every_cut(seq):
    """A document cut at any byte is refused in one line (or holds nothing and is refused as empty): never a
    shorter valid document."""
    state = AppState(seq)
    for k, frame_id in enumerate(seq.ids):
        state.set_frame(k)
        state.set_pose([0.001 * k, 0.0, 0.7], [0, 0, 0, 1])
    state.close()
    path = state.path
    text = path.read_bytes()
    lines = text.decode().splitlines()
    assert lines[0] == FIRST_LINE and lines[-1] == END_MARKER
    assert len(load_annotation(path).frames) == len(seq.ids)
    rng = np.random.default_rng(0)
    line_ends = [i + 1 for i, byte in enumerate(text) if byte == ord("\n")]
    cuts = sorted(set(line_ends[:-1]) | set(rng.integers(0, len(text), 150).tolist()))
    truncated = path.with_name("truncated.yaml")
    for cut in cuts:
        truncated.write_bytes(text[:cut])
        with pytest.raises(InputError) as refused:
            load_annotation(truncated)
        message = str(refused.value)
        assert "\n" not in message and "truncated.yaml" in message, message
    truncated.write_bytes(text + b"\n\n")  # trailing blank lines are not a cut
    assert len(load_annotation(truncated).frames) == len(seq.ids)


@pytest.mark.parametrize("content", ["", "\n\n", "# nothing but a comment\n", FIRST_LINE + "\n"])
def test_an_empty_document_is_refused_in_one_line(seq, content, capsys):
    path = seq.root / "annotation.yaml"
    path.write_text(content)
    with pytest.raises(InputError, match="annotation document is empty") as refused:
        AppState(seq)
    assert "annotation.yaml" in str(refused.value) and "\n" not in str(refused.value)
    from annotate.cli import main
    from sequences.errors import run_cli

    with pytest.raises(SystemExit) as exit_info:
        run_cli(main, [str(seq.root), "--port", "0"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "empty" in err and "\n" not in err


def test_documents_written_before_the_marker_still_load_and_gain_it_at_the_next_save(seq):
    path = seq.root / "annotation.yaml"
    path.write_text(OLD_DOCUMENT)
    state = AppState(seq)
    assert set(state.annotation.frames) == {"0000001", "0000002"}
    assert state.annotation.frames["0000002"].extra["fitness"] == 0.9
    state.set_extents([0.08, 0.12, 0.07])
    state.close()
    assert path.read_text().startswith(FIRST_LINE) and path.read_text().rstrip().endswith(END_MARKER)
    assert path.with_name("annotation.yaml.orig").read_text() == OLD_DOCUMENT  # as the session found it
