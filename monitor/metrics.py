"""Prometheus text metrics of a running monitor on 127.0.0.1 (``[monitor] prometheus_port``)."""

from __future__ import annotations

import asyncio
import logging
import math

log = logging.getLogger(__name__)


def metrics_text(status: dict) -> str:
    """The Prometheus exposition text of a :meth:`Monitor.status` dict."""
    lines = []

    def metric(name, help_text, value, kind="gauge", labels=""):
        if value is None or (isinstance(value, float) and not math.isfinite(value)):
            return
        lines.append(f"# HELP hybridcomp_monitor_{name} {help_text}")
        lines.append(f"# TYPE hybridcomp_monitor_{name} {kind}")
        lines.append(f"hybridcomp_monitor_{name}{labels} {float(value):.9g}")

    metric("machine_time_seconds", "machine time of the last processed sample [s]", status.get("last_time_s"))
    metric("delta_t_kelvin", "last |T_actual - T_reference| of the active CD set [K]", status.get("last_delta_T_K"))
    for k, v in (status.get("offsets_um") or {}).items():
        metric(f"offset_{k}", f"last compensation offset {k} [um]", v)
    for name in ("readings", "compensations", "monitorings", "switches", "generations", "reconnects",
                 "dropped_repeated", "dropped_backwards", "dropped_invalid"):
        metric(f"{name}_total", f"number of {name.replace('_', ' ')}", status.get(name), "counter")
    metric("decision_seconds_max", "slowest monitoring decision [s]", status.get("max_decision_s"))
    metric("degraded_sensors", "number of degraded sensors", len(status.get("degraded") or []))
    metric("regeneration_running", "1 while a generation job runs", int(bool(status.get("regeneration_running"))))
    return "\n".join(lines) + "\n"


async def serve_metrics(monitor, port: int, host: str = "127.0.0.1") -> asyncio.AbstractServer:
    """Serve ``GET /metrics`` (any path) with :func:`metrics_text` of ``monitor.status()``."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 5.0)
            body = metrics_text(monitor.status()).encode()
            writer.write(b"HTTP/1.1 200 OK\r\nContent-Type: text/plain; version=0.0.4\r\n"
                         + f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode() + body)
            await writer.drain()
        except (TimeoutError, asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(handle, host, port)
    log.info("metrics on http://%s:%d/metrics", host, port)
    return server
