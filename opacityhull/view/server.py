"""Serve a viewer bundle on 127.0.0.1 with the standard library's HTTP server, in a thread."""

from __future__ import annotations

import functools
import http.server
import logging
import threading
from pathlib import Path

from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = ["BundleServer"]


class _Handler(http.server.SimpleHTTPRequestHandler):
    extensions_map = {
        **http.server.SimpleHTTPRequestHandler.extensions_map,
        ".js": "text/javascript",
        ".json": "application/json",
        ".bin": "application/octet-stream",
    }

    def log_message(self, fmt, *args):  # requests go to the log, not to stderr
        log.debug("%s " + fmt, self.address_string(), *args)

    def end_headers(self):
        self.send_header("Cache-Control", "no-store")
        super().end_headers()


class BundleServer:
    """``with BundleServer(dir, port=0) as s: s.url`` — a threaded static server bound to
    127.0.0.1 (port 0: any free port)."""

    def __init__(self, directory, *, port: int = 0):
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise InputError(f"viewer bundle {self.directory} is not a folder")
        if not 0 <= int(port) <= 65535:
            raise InputError(f"--port {port}: expected 0..65535")
        handler = functools.partial(_Handler, directory=str(self.directory))
        try:
            self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", int(port)), handler)
        except OSError as e:
            raise InputError(f"--port {port}: cannot listen on 127.0.0.1:{port} ({e.strerror})") from None
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="opacityhull-view", daemon=True)
        self.thread.start()

    @property
    def port(self) -> int:
        return self.httpd.server_address[1]

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
