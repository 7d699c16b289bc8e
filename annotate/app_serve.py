"""``annotate [SEQ]``: open the sequence, start the viser server on the asked port, print the URL, serve until Ctrl-C.

The server takes the port asked for or none: viser would move to the next free port, where tabs left open on the
asked one (after a restart) could never reconnect. A restarting server gets a few seconds for its predecessor
to let the port go. Bound beyond loopback, the server needs a token (:mod:`.origin_guard`), printed in the URL.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path

import viser

from sequences.errors import InputError
from sequences.reader import open_sequence

from .app import App
from .origin_guard import ALL_INTERFACES, TOKEN_PARAMETER, guard_origins, is_loopback, require_token

#: Seconds to wait for the asked port to be free (a server being restarted lets it go in a moment).
PORT_WAIT_S = 5.0


def resolve_sequence(path: str | None) -> Path:
    """The sequence folder to serve: the given one, or the bundled sample."""
    if path is not None:
        return Path(path)
    try:
        from sequences.sample import sample_sequence

        print("annotate: no sequence given: opening the bundled sample (generated on first use)", flush=True)
        return Path(sample_sequence())
    except ImportError as error:
        raise InputError(None, f"no sequence given and the bundled sample is not available ({error}); run: annotate SEQ") from error


def port_is_free(host: str, port: int) -> bool:
    """Whether a server could bind ``host``:``port`` now (as asyncio does: with SO_REUSEADDR)."""
    try:
        infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except OSError:
        return True  # an unresolvable host: the server's own bind reports it
    for family, kind, proto, _, address in infos:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind(address)
            except OSError:
                return False
    return True


def wait_for_port(host: str, port: int, seconds: float | None = None) -> None:
    """Return once ``host``:``port`` is free; InputError when it is still taken after ``seconds`` (default PORT_WAIT_S)."""
    deadline = time.monotonic() + (PORT_WAIT_S if seconds is None else seconds)
    while not port_is_free(host, port):
        if time.monotonic() > deadline:
            raise InputError(None, f"port {port} on {host or 'every interface'} is in use (another annotate server?): "
                                   "stop it, or choose another port with --port")
        time.sleep(0.2)


def urls(host: str, port: int, token: str | None) -> list[str]:
    """The URLs to print: this machine's first, then the machine's name when bound on every interface."""
    query = f"/?{TOKEN_PARAMETER}={token}" if token else ""
    if host in ALL_INTERFACES:
        return [f"http://127.0.0.1:{port}{query}", f"http://{socket.gethostname()}:{port}{query}"]
    shown = f"[{host}]" if ":" in host and not host.startswith("[") else host
    return [f"http://{shown}:{port}{query}"]


def start_server(host: str, port: int) -> tuple[viser.ViserServer, str | None]:
    """The viser server on ``host``:``port`` (0: any free port) with the Origin guard, and its token (None on loopback)."""
    guard_origins()  # a page the user visits elsewhere must not drive the tool
    token = None
    if not is_loopback(host):
        token = require_token(host)
        print(f"annotate: warning: serving on {host or 'every interface'}: anyone who can reach this machine on the port "
              "and has the URL below (with its token) can open and edit the document (use --host 127.0.0.1 to serve "
              "this machine only)", flush=True)
    if port:
        wait_for_port(host, port)
    server = viser.ViserServer(host=host, port=port, label="annotate", verbose=False)
    if port and server.get_port() != port:  # taken between the check and the bind: viser moved on
        server.stop()
        raise InputError(None, f"port {port} on {host or 'every interface'} is in use (another annotate server?): "
                               "stop it, or choose another port with --port")
    return server, token


def serve(args) -> int:
    """Serve the tool for ``args.sequence`` (None: the bundled sample) until interrupted."""
    root = resolve_sequence(args.sequence)
    sequence = open_sequence(root)
    # read the first frame now: an unreadable sequence is refused before anything is served
    sequence.color(0)
    sequence.depth_raw(0)
    sequence.check_depth_scale()
    server, token = start_server(args.host, args.port)
    try:
        app = App(server, sequence, getattr(args, "annotation", None))
    except BaseException:
        server.stop()
        raise
    print(f"annotate: serving {sequence.root} ({len(sequence)} frames), document {app.state.path}", flush=True)
    if app.state.read_only:
        print(f"annotate: {app.state.read_only}", flush=True)
    first, *others = urls(args.host, server.get_port(), token)
    print(f"annotate: open {first}", flush=True)
    for url in others:
        print(f"annotate: from another machine: {url}", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        app.close()
        server.stop()
    return 0
