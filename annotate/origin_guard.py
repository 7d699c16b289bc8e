"""The browser tool answers its own pages only: websocket handshakes from another Origin are refused, and beyond
loopback every request needs the session's token.

A web page the user visits could otherwise open a websocket to ``ws://127.0.0.1:8080`` and drive the tool (edit
and overwrite documents): browsers send the page's Origin with every handshake but do not stop cross-origin
websockets. viser opens its server through ``websockets.asyncio.server.serve``; :func:`guard_origins` wraps that
call so that it passes ``origins``: the tool's own addresses on the bound port (loopback names, and the machine's
names and addresses when bound beyond loopback), and no Origin at all (a script, not a browser).

Bound beyond loopback, anyone on the network could open the page itself. :func:`require_token` makes a random
token for a bind address, as Jupyter does, and keeps it in the user's cache (``tokens/`` under
``sequences.sample.cache_dir()``, readable by the user only), so a restarted server takes the same one and an open
tab reconnects; delete the file to make a new one. The server then answers a request (the page, its files, the websocket
handshake) only when it carries the token: ``?token=...`` in its URL, or the cookie the page's answer sets (viser's
client builds its websocket URL from the page's without the query, and a browser sends the cookie with the
handshake). The cookie is ``HttpOnly`` and ``SameSite=Strict``, named after the port, as cookies are per host.
"""

from __future__ import annotations

import hmac
import http
import inspect
import ipaddress
import os
import re
import secrets
import socket
import tempfile
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

LOOPBACK = ("127.0.0.1", "localhost", "[::1]")
ALL_INTERFACES = ("", "0.0.0.0", "::")
#: The URL's query parameter that carries the token.
TOKEN_PARAMETER = "token"
#: Tokens required per bind address (the ``host`` given to the server); loopback addresses have none.
_tokens: dict[str, str] = {}


def is_loopback(host: str | None) -> bool:
    """Whether binding on ``host`` serves this machine only (127.0.0.0/8, ::1, localhost)."""
    if host in ("localhost", "[::1]"):
        return True
    try:
        return ipaddress.ip_address((host or "").strip("[]")).is_loopback
    except ValueError:  # a name, or "" (every interface)
        return False


def own_origins(host: str, port: int) -> list:
    """The Origins of pages the tool itself serves on ``host``:``port``, and None (no Origin header). With port 0 (the
    system picks one when binding, after this list is made) any port of those hosts, as patterns."""
    names = set(LOOPBACK)
    if host in ALL_INTERFACES:
        hostname = socket.gethostname()
        names |= {hostname, socket.getfqdn()}
        try:
            names |= {address[4][0] for address in socket.getaddrinfo(hostname, None)}
        except OSError:  # no resolver: the loopback names and the host's name still work
            pass
    elif host not in LOOPBACK:
        names.add(host)
    origins: list = []
    for name in sorted(names):
        shown = f"[{name}]" if ":" in name and not name.startswith("[") else name
        origins.append(f"http://{shown}:{port}" if port else re.compile(rf"http://{re.escape(shown)}:\d+"))
    return [*origins, None]


def require_token(host: str) -> str:
    """The token every server this process binds on ``host`` requires from now on: the one kept for ``host`` (see the
    module notes), else a new one, kept."""
    host = host or ""
    if host not in _tokens:
        _tokens[host] = _kept_token(host)
    return _tokens[host]


def token_file(host: str) -> Path:
    """Where the token of bind address ``host`` is kept."""
    from sequences.sample import cache_dir

    return cache_dir() / "tokens" / f"{re.sub(r'[^A-Za-z0-9._-]', '_', host) or 'all'}.token"


def _kept_token(host: str) -> str:
    """The token kept for ``host`` (a file of this user's, mode 0600), or a new one kept: written to a temporary name
    and linked into place, so of two servers starting at once the second takes the first's."""
    path = token_file(host)
    kept = _read_token(path)
    if kept is not None:
        return kept
    token = secrets.token_urlsafe(24)
    temporary = None
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)  # mode 0600
        with os.fdopen(fd, "w") as handle:
            handle.write(token + "\n")
        if path.exists():  # damaged or not this user's alone: replaced
            os.replace(temporary, path)
            temporary = None
        else:
            try:
                os.link(temporary, path)  # fails where another server kept one meanwhile: take that one
            except FileExistsError:
                return _read_token(path) or token
    except OSError:  # a cache that cannot be written: the token lives as long as this process
        pass
    finally:
        if temporary is not None:
            try:
                os.unlink(temporary)
            except OSError:
                pass
    return token


def _read_token(path: Path) -> str | None:
    """The token in ``path`` where it is one and the file is this user's alone (owner, mode 0600), else None."""
    try:
        info = path.stat()
        if info.st_uid != os.getuid() or info.st_mode & 0o077:
            return None
        kept = path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None
    return kept if re.fullmatch(r"[A-Za-z0-9_-]{32,}", kept) else None


def cookie_name(port: int) -> str:
    """The cookie that carries the token of the server on ``port``."""
    return f"annotate_token_{int(port)}"


def _given_tokens(request, port: int) -> tuple[list[str], list[str]]:
    """(tokens in the request's URL query, tokens in its cookie for ``port``)."""
    query = parse_qs(urlsplit(request.path).query).get(TOKEN_PARAMETER, [])
    name = cookie_name(port)
    cookies = []
    for header in request.headers.get_all("Cookie"):
        for part in header.split(";"):
            key, _, value = part.strip().partition("=")
            if key == name:
                cookies.append(value)
    return query, cookies


def _matches(given: list[str], token: str) -> bool:
    return any(hmac.compare_digest(value.encode(), token.encode()) for value in given)


def token_guard(process_request, token: str):
    """Wrap a websockets ``process_request`` (None: none) so that requests without ``token`` are answered 403; the
    answer to a request with the token in its URL sets the cookie that carries it."""

    async def guarded(connection, request):
        port = connection.local_address[1]
        query, cookies = _given_tokens(request, port)
        in_query = _matches(query, token)
        if not (in_query or _matches(cookies, token)):
            return connection.respond(http.HTTPStatus.FORBIDDEN, "annotate: this server needs its token: open the URL it printed when it "
                                                                 f"started (with ?{TOKEN_PARAMETER}=...)\n")
        response = process_request(connection, request) if process_request is not None else None
        if inspect.isawaitable(response):
            response = await response
        if response is not None and in_query:
            response.headers["Set-Cookie"] = f"{cookie_name(port)}={token}; Path=/; HttpOnly; SameSite=Strict"
        return response

    return guarded


def guard_origins() -> None:
    """Make every websocket server this process starts refuse handshakes from other Origins, and requests without
    the token where :func:`require_token` made one for its host (idempotent)."""
    import websockets.asyncio.server as server

    original = server.serve
    if getattr(original, "guards_origins", False):
        return

    class GuardedServe(original):  # serve is a class: keep it one, for `async with` and isinstance
        guards_origins = True

        def __init__(self, handler, host=None, port=None, **kwargs):
            kwargs.setdefault("origins", own_origins(host or "", int(port or 0)))
            token = _tokens.get(host or "")
            if token is not None:
                kwargs["process_request"] = token_guard(kwargs.get("process_request"), token)
            super().__init__(handler, host, port, **kwargs)

    server.serve = GuardedServe
