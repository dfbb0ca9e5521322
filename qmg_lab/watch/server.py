"""The Bokeh server of `qmg-lab watch`: one page per browser session, each following the run file itself.

Bokeh (bokeh.server.server.Server, a Tornado server) pushes each update over a websocket; the page needs no
JavaScript of ours. It listens on 127.0.0.1 unless a host is given on purpose (then anyone who can reach that
address sees the page: it shows the run and cannot change anything, but it is not protected by a password).
"""

from __future__ import annotations

import logging
import socket
from pathlib import Path

from bokeh.application import Application
from bokeh.application.handlers.function import FunctionHandler
from bokeh.document import Document
from bokeh.server.server import Server

from qmg_lab.watch.page import WatchPage

LOOPBACK = "127.0.0.1"
DEFAULT_PORT = 5006
#: what Bokeh's websocket handler logs at WARNING when a closed tab's session still gets the page's update: the
#: session ends by itself within check_unused_sessions_milliseconds, so it is nothing to act on
CLOSED_TAB = "Failed sending message as connection was closed"


class _ClosedTabFilter(logging.Filter):
    """Drops exactly CLOSED_TAB from bokeh.server.views.ws; every other record passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != CLOSED_TAB


def quiet_closed_tabs() -> None:
    """Install the CLOSED_TAB filter on Bokeh's websocket logger (once)."""
    log = logging.getLogger("bokeh.server.views.ws")
    if not any(isinstance(f, _ClosedTabFilter) for f in log.filters):
        log.addFilter(_ClosedTabFilter())


def free_port(host: str = LOOPBACK, start: int = DEFAULT_PORT, tries: int = 50) -> int:
    """The first port from `start` that can be bound on host (the OS's choice if none of `tries` can)."""
    for port in range(start, start + tries):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def make_server(path: Path, host: str = LOOPBACK, port: int = DEFAULT_PORT) -> Server:
    """A started-but-not-running server of the page of `path` at http://host:port/ (call .io_loop.start())."""
    quiet_closed_tabs()

    def session(doc: Document) -> None:
        WatchPage(path).attach(doc)

    origins = [f"{LOOPBACK}:{port}", f"localhost:{port}"] if host == LOOPBACK else ["*"]
    server = Server(
        {"/": Application(FunctionHandler(session))},
        address=host,
        port=port,
        allow_websocket_origin=origins,
        num_procs=1,
        # a closed tab's session (and its once-a-second poll of the file) ends within seconds
        check_unused_sessions_milliseconds=2000,
        unused_session_lifetime_milliseconds=2000,
    )
    server.start()
    return server


def url(host: str, port: int) -> str:
    shown = socket.gethostname() if host in ("0.0.0.0", "::") else host
    return f"http://{shown}:{port}/"
