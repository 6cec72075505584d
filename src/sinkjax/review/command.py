"""``sinkjax review`` (conventions §3): arguments, the socket on 127.0.0.1 and uvicorn.

Imports no server library until it runs, so ``sinkjax -h`` works without the ``review`` extra;
then a missing one is a usage error naming the extra to install.
"""

from __future__ import annotations

import argparse
import socket
import threading
import webbrowser
from typing import Any

EXTRA_HINT = "pip install 'sinkjax[review]'"


def add_cli_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "paths",
        nargs="+",
        metavar="PATH",
        help="recordings: directories of images (with their rig.toml) or image files",
    )
    p.add_argument(
        "--results", metavar="results.csv", help="a results CSV of these frames to review"
    )
    p.add_argument(
        "--labels",
        metavar="LABELS.csv",
        help="where 'save' writes labels (default: LABELS.csv in the first recording's folder)",
    )
    p.add_argument(
        "--rig", metavar="RIG.toml", help="rig for inputs without a rig.toml of their own"
    )
    p.add_argument(
        "--method",
        choices=("soft", "classic"),
        default="soft",
        help="method of the page's 'measure' button (default: soft)",
    )
    p.add_argument("--port", type=int, default=0, metavar="N", help="port (default: a free one)")
    p.add_argument("--no-browser", action="store_true", help="only print the page's address")


def run_cli(args: argparse.Namespace) -> int:
    """Serve the page until Ctrl-C; exit code 0, or 2 (via UsageError) for unusable arguments."""
    from ..app.cli import EXIT_OK, UsageError

    try:
        import starlette  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as e:
        raise UsageError(
            f"'sinkjax review' needs the review extra ({e.name} is not installed): {EXTRA_HINT}"
        ) from e
    from .server import create_app
    from .session import ReviewSession

    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be 0-65535 (0: a free port), got {args.port}")
    session = ReviewSession(
        args.paths, results=args.results, labels=args.labels, rig_path=args.rig, method=args.method
    )
    try:
        sock = bind(args.port)
    except OSError as e:
        raise UsageError(
            f"cannot listen on 127.0.0.1:{args.port} ({e.strerror or e}); pick another --port "
            "or leave it out for a free one"
        ) from e
    server = Server(create_app(session), sock)
    measured = sum(r is not None for r in session.results)
    print(
        f"sinkjax review: {len(session.frames)} frames in {len(session.recordings)} "
        f"recording(s), {measured} with results; labels -> {session.labels.path}"
    )
    print(f"open {server.url}  (Ctrl-C to stop)", flush=True)
    if not args.no_browser:
        threading.Timer(0.5, webbrowser.open, args=(server.url,)).start()
    try:
        server.run()
    finally:
        sock.close()
    return EXIT_OK


def bind(port: int = 0) -> socket.socket:
    """A listening socket on 127.0.0.1 (``port`` 0: a free one). Raises OSError if taken."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", port))
    sock.listen(64)
    return sock


class Server:
    """uvicorn serving ``app`` on an already bound socket; :meth:`url` says where."""

    def __init__(self, app: Any, sock: socket.socket) -> None:
        import uvicorn

        self.sock = sock
        self._server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off"))
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self.sock.getsockname()[:2]
        return f"http://{host}:{port}/"

    def run(self) -> None:
        """Serve until interrupted (Ctrl-C)."""
        self._server.run(sockets=[self.sock])

    def start(self) -> Server:
        """Serve in a background thread (tests); returns once it accepts connections."""
        self._thread = threading.Thread(target=self.run, name="sinkjax-review", daemon=True)
        self._thread.start()
        while not self._server.started:
            if not self._thread.is_alive():
                raise RuntimeError("the review server stopped while starting")
            self._thread.join(0.02)
        return self

    def stop(self) -> None:
        self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(10)
        self.sock.close()
