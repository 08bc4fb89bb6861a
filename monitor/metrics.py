"""The monitor's Prometheus metrics, written by the official client library (``prometheus_client``, extra ``live``).

Two endpoints give them: the daemon's own ``[monitor] prometheus_port`` (:func:`serve_metrics`, the running
process's counters from :meth:`Monitor.status`, on 127.0.0.1) and ``hybridcomp monitor serve``'s ``/metrics``
(:func:`live_families`, the daemon's record as :class:`hybridcomp.monitor.live.LiveReader` reads it). The figures
both have are built by the same functions (:func:`common_families`) under the same names, so
``grafana_dashboard.json`` draws them from either. A collector builds its families at every scrape
(:func:`registry`); :func:`exposition` writes them in the library's text format.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Iterable, Mapping

from hybridcomp.errors import HybridcompError
from hybridcomp.models.layout import DRIFT_COLUMNS
from hybridcomp.monitor.live import _num as _finite  # a finite float, else None

log = logging.getLogger(__name__)

PREFIX = "hybridcomp_monitor_"
INSTALL = 'pip install -e ".[live]"'  # the extra that brings prometheus_client
#: the daemon's counters exposed as ``hybridcomp_monitor_<name>_total``
STATUS_COUNTERS = ("readings", "compensations", "monitorings", "switches", "generations", "reconnects",
                   "dropped_repeated", "dropped_backwards", "dropped_invalid")


class MetricsUnavailable(HybridcompError, RuntimeError):
    """Prometheus metrics were asked for without ``prometheus_client`` installed; the message says what to install."""


def require_client(what: str) -> None:
    """Raise :class:`MetricsUnavailable` naming ``what`` and the extra when ``prometheus_client`` is missing."""
    try:
        import prometheus_client  # noqa: F401
    except ImportError as exc:
        raise MetricsUnavailable(f"{what} needs prometheus_client, which is not installed: {INSTALL} "
                                 "(or pip install prometheus-client)") from exc


# ============================================================================================ families
def gauge(name: str, doc: str, value):
    """A gauge ``hybridcomp_monitor_<name>`` without labels; no sample when ``value`` is None or not finite."""
    from prometheus_client.core import GaugeMetricFamily

    g = GaugeMetricFamily(PREFIX + name, doc, labels=[])
    v = _finite(value)
    if v is not None:
        g.add_metric([], v)
    return g


def labelled(name: str, doc: str, label: str, values: Mapping, kind: str = "gauge"):
    """A gauge (or ``kind="counter"``) ``hybridcomp_monitor_<name>`` with one sample per finite value of ``values``."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    fam = (CounterMetricFamily if kind == "counter" else GaugeMetricFamily)(PREFIX + name, doc, labels=[label])
    for key, value in values.items():
        v = _finite(value)
        if v is not None:
            fam.add_metric([str(key)], v)
    return fam


def common_families(offsets_um: Mapping | None, error_um: Mapping | None, delta_T_K, machine_time_s,
                    n_degraded: int, observer_flag) -> list:
    """The figures both endpoints give: the offsets per axis, the predicted error, ΔT, machine time, sensors, observer.

    Parameters
    ----------
    offsets_um : the offsets written last, ``{"dx_um": ..., ...}`` [µm] (label ``axis``: dx, dy, dz)
    error_um : the active set's predicted error at the last decision, ``{"interval_um", "forecast_um"}`` [µm]
    delta_T_K : the last |T_actual − T_reference| of the active set [K]
    machine_time_s : machine time of the last sample [s]
    n_degraded : the number of degraded sensors
    observer_flag : a non-empty flag while the observer is not trusted
    """
    off, err = offsets_um or {}, error_um or {}
    return [
        labelled("offset_micrometers", "compensation offset written last (predicted TCP drift; the control subtracts "
                 "it) [µm]", "axis", {c.removesuffix("_um"): off.get(c) for c in DRIFT_COLUMNS}),
        labelled("predicted_error_micrometers", "the active CD set's predicted compensation error at the last "
                 "decision [µm]", "horizon", {k: err.get(f"{k}_um") for k in ("interval", "forecast")}),
        gauge("delta_t_kelvin", "last |T_actual - T_reference| of the active CD set [K]", delta_T_K),
        gauge("machine_time_seconds", "machine time of the last sample [s]", machine_time_s),
        gauge("degraded_sensors", "number of degraded sensors", n_degraded),
        gauge("observer_flagged", "1 while the observer is not trusted, else 0", float(bool(observer_flag))),
    ]


def status_families(status: Mapping) -> list:
    """The families of the daemon's own endpoint from a :meth:`Monitor.status` dict."""
    from prometheus_client.core import CounterMetricFamily

    out = common_families(status.get("offsets_um"), status.get("last_error_um"), status.get("last_delta_T_K"),
                          status.get("last_time_s"), len(status.get("degraded") or []), status.get("observer_flag"))
    for name in STATUS_COUNTERS:
        if _finite(status.get(name)) is not None:
            out.append(CounterMetricFamily(f"{PREFIX}{name}", f"number of {name.replace('_', ' ')}",
                                           value=float(status[name])))
    out.append(gauge("decision_seconds_max", "slowest monitoring decision [s]", status.get("max_decision_s")))
    out.append(gauge("regeneration_running", "1 while a generation job runs", int(bool(status.get("regeneration_running")))))
    return out


def live_families(snap: Mapping, event_counts: Mapping[str, int]) -> list:
    """The families of ``monitor serve``'s ``/metrics`` from a :meth:`LiveReader.snapshot` and its event counts."""
    h, latest, lim = snap["health"], snap["latest"], snap["limits"]
    return [
        *common_families(latest["offsets_um"], latest["error_um"], latest["delta_T_K"],
                         None if latest["t_h"] is None else latest["t_h"] * 3600.0, len(h["degraded"] or []),
                         snap["observer_flag"]),
        labelled("error_limit_micrometers", "limits of the predicted error: keep (interval), forecast, hard, reject "
                 "[µm]", "limit", {k: lim.get(f"{k}_um") for k in ("keep", "forecast", "hard", "reject")}),
        labelled("sensor_residual_kelvin", "sensor as measured minus the observer's estimate [K]", "sensor",
                 {s["name"]: s["residual_K"] for s in snap["sensors_now"]}),
        gauge("model_drift_limit_kelvin", "|sensor - estimate| above which the model has drifted [K]",
              lim.get("model_drift_K")),
        labelled("events", "events the monitor logged, by kind", "kind", dict(sorted(event_counts.items())), "counter"),
        gauge("seconds_since_applied_offset", "wall time since a sink last took an offset [s]",
              h["seconds_since_offset"]),
        gauge("seconds_since_heartbeat", "wall time since the daemon's last heartbeat [s]", h["seconds_since_heartbeat"]),
        gauge("store_queue_length", "database writes the daemon has queued (0: the database keeps up)",
              h["store_backlog"]),
        gauge("healthy", "1 while an offset was applied within stale_after_s, else 0",
              1.0 if h["status"] == "healthy" else 0.0),
        gauge("running", "1 while the daemon runs (its last heartbeat says so), else 0",
              None if h["running"] is None else float(bool(h["running"]))),
        gauge("failsafe", "1 while the active set is known wrong and not applied, else 0", float(bool(snap["failsafe"]))),
    ]


# ============================================================================================ registry, text
def registry(families: Callable[[], Iterable]):
    """A ``prometheus_client`` registry of one collector that calls ``families()`` at every scrape."""
    from prometheus_client.core import CollectorRegistry

    class Collector:
        def collect(self):
            yield from families()

        def describe(self):
            return []

    reg = CollectorRegistry(auto_describe=False)
    reg.register(Collector())
    return reg


def exposition(reg) -> tuple[bytes, str]:
    """The Prometheus text of a registry and its content type, as the client library writes them."""
    from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

    return generate_latest(reg), CONTENT_TYPE_LATEST


def metrics_text(status: Mapping) -> str:
    """The Prometheus exposition text of a :meth:`Monitor.status` dict."""
    return exposition(registry(lambda: status_families(status)))[0].decode()


async def serve_metrics(monitor, port: int, host: str = "127.0.0.1") -> asyncio.AbstractServer:
    """Serve ``GET /metrics`` (any path) with the families of ``monitor.status()`` at every request.

    Raises
    ------
    MetricsUnavailable
        ``prometheus_client`` is not installed (the server does not start).
    """
    require_client(f"[monitor] prometheus_port = {port}")
    reg = registry(lambda: status_families(monitor.status()))

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 5.0)
            body, ctype = exposition(reg)
            writer.write(f"HTTP/1.1 200 OK\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
                         "Connection: close\r\n\r\n".encode() + body)
            await writer.drain()
        except (TimeoutError, asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(handle, host, port)
    log.info("metrics on http://%s:%d/metrics", host, port)
    return server


__all__ = ["INSTALL", "MetricsUnavailable", "common_families", "exposition", "live_families", "metrics_text",
           "registry", "require_client", "serve_metrics", "status_families"]
