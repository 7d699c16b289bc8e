"""The browser tool answers its own pages only: websocket handshakes from another Origin are refused.

A web page the user visits could otherwise open a websocket to ``ws://127.0.0.1:8080`` and drive the tool (edit
and overwrite documents): browsers send the page's Origin with every handshake but do not stop cross-origin
websockets. viser opens its server through ``websockets.asyncio.server.serve``; :func:`guard_origins` wraps that
call so that it passes ``origins``: the tool's own addresses on the bound port (loopback names, and the machine's
names and addresses when bound beyond loopback), and no Origin at all (a script, not a browser).
"""

from __future__ import annotations

import re
import socket

LOOPBACK = ("127.0.0.1", "localhost", "[::1]")
ALL_INTERFACES = ("", "0.0.0.0", "::")


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


def guard_origins() -> None:
    """Make every websocket server this process starts refuse handshakes from other Origins (idempotent)."""
    import websockets.asyncio.server as server

    original = server.serve
    if getattr(original, "guards_origins", False):
        return

    class GuardedServe(original):  # serve is a class: keep it one, for `async with` and isinstance
        guards_origins = True

        def __init__(self, handler, host=None, port=None, **kwargs):
            kwargs.setdefault("origins", own_origins(host or "", int(port or 0)))
            super().__init__(handler, host, port, **kwargs)

    server.serve = GuardedServe
