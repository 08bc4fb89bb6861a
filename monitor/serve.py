"""``hybridcomp monitor serve``: the monitor's live view, a read-only web page and Prometheus metrics.

A :class:`http.server.ThreadingHTTPServer` (the standard library, no web framework) serves

* ``/``: one self-contained HTML page (``live.html`` beside this module: its own plotting code, inline SVG, no
  network) that polls ``/api/live`` every ``interval_s`` and draws the offsets per axis, the active CD set's
  predicted error with its limits, the sensors against the observer's estimate, the probes, the events of the last
  shift and the health;
* ``/api/live``: :meth:`hybridcomp.monitor.live.LiveReader.snapshot` as JSON;
* ``/metrics``: the figures for Prometheus, written by the official client library (``prometheus_client``, extra
  ``live``; :func:`hybridcomp.monitor.metrics.live_families`); ``monitor/grafana_dashboard.json`` shows them in
  Grafana.

Safe by default: only GET (anything else is 405; nothing on the page changes the machine or the database, which is
opened read-only), bound to 127.0.0.1 unless told otherwise, a token required when bound to any other address
(``Authorization: Bearer <token>`` or ``?token=<token>``), no file path or database URL in what it sends
(:func:`hybridcomp.monitor.live.scrub`).
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import logging
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import parse_qs, urlsplit

from hybridcomp.errors import HybridcompError
from hybridcomp.monitor.live import LiveReader
from hybridcomp.monitor.metrics import INSTALL

log = logging.getLogger(__name__)

MIN_TOKEN_CHARS = 16
DEFAULT_PORT = 8765
SECURITY_HEADERS = {
    # the page's own inline script and style, requests to this server only, nothing from elsewhere
    "Content-Security-Policy": "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
                               "connect-src 'self'; img-src 'self' data:; base-uri 'none'; form-action 'none'; "
                               "frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


class ServeError(HybridcompError, ValueError):
    """The server refuses to start (an address other than loopback without a token, a short token)."""


def is_loopback(host: str) -> bool:
    """Whether ``host`` is this machine only (127.0.0.0/8, ::1, ``localhost``)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_binding(host: str, token: str | None) -> None:
    """Refuse another address than loopback without a token, and a token shorter than :data:`MIN_TOKEN_CHARS`."""
    if token is not None and len(token) < MIN_TOKEN_CHARS:
        raise ServeError(f"--token: at least {MIN_TOKEN_CHARS} characters (got {len(token)}); e.g. "
                         "python -c 'import secrets; print(secrets.token_urlsafe(24))'")
    if not is_loopback(host) and not token:
        raise ServeError(f"--host {host}: another address than loopback (127.0.0.1) is served only with --token (or "
                         "HYBRIDCOMP_MONITOR_TOKEN): anyone on the network could read the machine's state")


def page_html() -> str:
    """The live view's page (self-contained: its script, style and plotting code inline)."""
    return resources.files("hybridcomp.monitor").joinpath("live.html").read_text(encoding="utf-8")


# ============================================================================================ metrics
def metrics_registry(reader: LiveReader):
    """A ``prometheus_client`` registry whose collector reads :meth:`LiveReader.snapshot` at every scrape."""
    from hybridcomp.monitor.metrics import live_families, registry

    return registry(lambda: live_families(reader.snapshot(), reader.event_counts()))


# ============================================================================================ the server
class LiveServer(ThreadingHTTPServer):
    """The live view's HTTP server (a thread per request; stop it with :meth:`shutdown`)."""

    daemon_threads = True

    def __init__(self, reader: LiveReader, host: str = "127.0.0.1", port: int = DEFAULT_PORT, token: str | None = None,
                 interval_s: float = 2.0):
        check_binding(host, token)
        self.reader = reader
        self.token = token
        self.interval_s = float(interval_s)
        self.registry = None
        self.page = page_html().replace("__INTERVAL_MS__", str(int(round(self.interval_s * 1000))))
        super().__init__((host, port), Handler)

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{host}:{port}/"

    def metrics_text(self) -> tuple[bytes, str]:
        """The ``/metrics`` text and its content type (ImportError without ``prometheus_client``)."""
        from hybridcomp.monitor.metrics import exposition

        if self.registry is None:
            self.registry = metrics_registry(self.reader)
        return exposition(self.registry)


class Handler(BaseHTTPRequestHandler):
    """GET ``/``, ``/api/live``, ``/metrics``; every other method is refused (405)."""

    server: LiveServer
    server_version = "hybridcomp-live"
    sys_version = ""

    def log_message(self, format, *args):  # (the base class's names)
        log.debug("%s %s", self.address_string(), format % args)

    def _send(self, code: int, body: bytes, ctype: str, extra: dict | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        for k, v in {**SECURITY_HEADERS, **(extra or {})}.items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _authorised(self, query: dict) -> bool:
        token = self.server.token
        if not token:
            return True
        given = ""
        auth = self.headers.get("Authorization", "")
        if auth.startswith("Bearer "):
            given = auth[len("Bearer "):].strip()
        elif query.get("token"):
            given = query["token"][0]
        return hmac.compare_digest(given.encode(), token.encode())

    def do_GET(self):  # (the base class's name)
        url = urlsplit(self.path)
        query = parse_qs(url.query)
        if url.path == "/favicon.ico":
            self._send(204, b"", "image/x-icon")
            return
        if not self._authorised(query):
            self._send(401, b"a token is required: ?token=... or Authorization: Bearer ...\n", "text/plain; charset=utf-8",
                       {"WWW-Authenticate": "Bearer"})
            return
        try:
            if url.path in ("/", "/index.html"):
                self._send(200, self.server.page.encode(), "text/html; charset=utf-8")
            elif url.path == "/api/live":
                snap = self.server.reader.snapshot()
                self._send(200, json.dumps({**snap, "interval_s": self.server.interval_s},
                                           allow_nan=False).encode(), "application/json")
            elif url.path == "/metrics":
                try:
                    body, ctype = self.server.metrics_text()
                except ImportError:
                    self._send(503, f"/metrics needs prometheus_client: {INSTALL}\n".encode(), "text/plain; charset=utf-8")
                    return
                self._send(200, body, ctype)
            else:
                self._send(404, b"not found\n", "text/plain; charset=utf-8")
        except Exception as exc:  # one failed request, never the server
            log.exception("live view: %s failed", url.path)
            self._send(500, f"the live view could not read the monitor's record ({type(exc).__name__})\n".encode(),
                       "text/plain; charset=utf-8")

    do_HEAD = do_GET

    def _refuse(self):
        self._send(405, b"read-only: GET only\n", "text/plain; charset=utf-8", {"Allow": "GET, HEAD"})

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _refuse


def serve_in_thread(server: LiveServer) -> threading.Thread:
    """Run ``server`` on a daemon thread (tests; stop with ``server.shutdown()``)."""
    t = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, name="live-view", daemon=True)
    t.start()
    return t


__all__ = ["LiveServer", "ServeError", "check_binding", "is_loopback", "metrics_registry", "page_html",
           "serve_in_thread"]
