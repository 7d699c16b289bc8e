"""The server's doors: Origins, the token beyond loopback, the port it takes."""

from __future__ import annotations

import socket
import urllib.error
import urllib.request
from pathlib import Path

import pytest
import viser
import websockets.exceptions
import websockets.sync.client
from test_app_fixtures import make_sequence

from annotate.process import AnnotateProcess
from annotate.origin_guard import cookie_name, guard_origins, is_loopback, require_token
from sequences.errors import InputError

REPO = Path(__file__).resolve().parents[1]
PROTOCOL = f"viser-v{viser.__version__}"


def _get(url: str, cookie: str | None = None) -> tuple[int, dict]:
    """HTTP status and headers of a GET (no exception for 403)."""
    request = urllib.request.Request(url, headers={"Cookie": cookie} if cookie else {})
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, dict(response.headers)
    except urllib.error.HTTPError as error:
        return error.code, dict(error.headers)


def _handshake(url: str, origin: str | None, cookie: str | None = None) -> int:
    """101 when the websocket handshake is accepted, else the refusal's status."""
    headers = {"Cookie": cookie} if cookie else None
    try:
        with websockets.sync.client.connect(url, origin=origin, subprotocols=[PROTOCOL], additional_headers=headers, open_timeout=10):
            return 101
    except websockets.exceptions.InvalidStatus as refused:
        return refused.value.response.status_code if hasattr(refused, "value") else refused.response.status_code


def test_loopback_is_told_apart():
    assert all(is_loopback(h) for h in ("127.0.0.1", "127.0.1.1", "localhost", "::1", "[::1]"))
    assert not any(is_loopback(h) for h in ("0.0.0.0", "", "::", "192.168.1.5", "myhost"))


def test_a_loopback_server_needs_no_token():
    guard_origins()
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        port = server.get_port()
        status, headers = _get(f"http://127.0.0.1:{port}/")
        assert status == 200 and "Set-Cookie" not in headers
        assert _handshake(f"ws://127.0.0.1:{port}", f"http://127.0.0.1:{port}") == 101
    finally:
        server.stop()


def test_beyond_loopback_every_request_needs_the_token():
    """Without the token the page, its files and the websocket are refused; with it (in the URL, or the cookie the
    page's answer sets, as a browser sends it with the handshake) they are served."""
    guard_origins()
    token = require_token("0.0.0.0")
    server = viser.ViserServer(host="0.0.0.0", port=0, verbose=False)
    try:
        port = server.get_port()
        base, ws, origin = f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}", f"http://127.0.0.1:{port}"
        assert _get(f"{base}/")[0] == 403
        assert _get(f"{base}/index.html")[0] == 403
        assert _get(f"{base}/?token=wrong")[0] == 403
        assert _get(f"{base}/", cookie=f"{cookie_name(port)}=wrong")[0] == 403
        assert _get(f"{base}/", cookie=f"{cookie_name(port + 1)}={token}")[0] == 403  # another server's cookie
        status, headers = _get(f"{base}/?token={token}")
        assert status == 200
        cookie = headers["Set-Cookie"]
        assert cookie.startswith(f"{cookie_name(port)}={token};") and "HttpOnly" in cookie and "SameSite=Strict" in cookie
        sent = cookie.split(";")[0]
        assert _get(f"{base}/index.html", cookie=sent)[0] == 200
        assert _handshake(ws, origin) == 403
        assert _handshake(ws, origin, cookie=f"{cookie_name(port)}=wrong") == 403
        assert _handshake(ws, origin, cookie=sent) == 101
        assert _handshake(f"{ws}/?token={token}", origin) == 101
        assert _handshake(ws, "http://evil.example", cookie=sent) == 403  # the Origin check still holds
    finally:
        server.stop()



@pytest.mark.slow
def test_annotate_beyond_loopback_warns_and_prints_a_url_with_its_token(tmp_path):
    root, _ = make_sequence(tmp_path / "seq", frames=2)
    log = tmp_path / "annotate.log"
    process = AnnotateProcess([root, "--host", "0.0.0.0", "--port", "0"], log)
    try:
        match = process.printed(r"open (http://127\.0\.0\.1:(\d+))/\?token=([\w-]+)")
        base, token = match.group(1), match.group(3)
        assert "warning: serving on 0.0.0.0" in log.read_text()
        assert _get(f"{base}/")[0] == 403
        assert _get(f"{base}/?token={token}")[0] == 200
    finally:
        process.stop()


def test_a_taken_port_is_refused_not_moved(monkeypatch):
    """viser would serve on the next port, where a tab left open on the asked one never reconnects: refused in one line."""
    from annotate import app_serve

    monkeypatch.setattr(app_serve, "PORT_WAIT_S", 0.5)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert not app_serve.port_is_free("127.0.0.1", port)
        with pytest.raises(InputError, match=f"port {port} on 127.0.0.1 is in use"):
            app_serve.start_server("127.0.0.1", port)
    assert app_serve.port_is_free("127.0.0.1", port)


def test_the_token_is_kept_for_the_next_server(tmp_path, monkeypatch):
    """A restarted server (a new process: the tokens it made are gone) takes the kept token, so an open tab's cookie
    still opens it; the file is the user's alone; a damaged file gives a new token, kept in its place."""
    import stat

    from annotate import origin_guard

    monkeypatch.setenv("REDWOOD_GT_CACHE", str(tmp_path))
    monkeypatch.setattr(origin_guard, "_tokens", {})
    first = require_token("0.0.0.0")
    path = origin_guard.token_file("0.0.0.0")
    assert path.read_text().strip() == first and stat.S_IMODE(path.stat().st_mode) == 0o600
    monkeypatch.setattr(origin_guard, "_tokens", {})  # the next process
    assert require_token("0.0.0.0") == first
    assert require_token("192.168.1.5") != first  # one per bind address
    path.write_text("short\n")
    monkeypatch.setattr(origin_guard, "_tokens", {})
    renewed = require_token("0.0.0.0")
    assert renewed != first and len(renewed) >= 32 and path.read_text().strip() == renewed
    path.chmod(0o644)  # readable by others: not trusted, replaced
    monkeypatch.setattr(origin_guard, "_tokens", {})
    third = require_token("0.0.0.0")
    assert third != renewed and stat.S_IMODE(path.stat().st_mode) == 0o600 and path.read_text().strip() == third
    assert sorted(p.name for p in path.parent.iterdir()) == sorted([path.name, origin_guard.token_file("192.168.1.5").name])
