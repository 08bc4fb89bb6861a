"""The monitoring daemon: compensation from the active CDs, the structure model watching whether they still fit.

* :mod:`hybridcomp.monitor.decisions` — every decision as a pure function (offset clamp and rate limit,
  sensor faults, time stamps, keep/switch/regenerate, model drift, reconnect backoff)
* :mod:`hybridcomp.monitor.config` — the TOML configuration
* :mod:`hybridcomp.monitor.sources` — replay of a trace CSV, OPC UA client; the injected clock
* :mod:`hybridcomp.monitor.sinks` — JSON lines, CSV, OPC UA
* :mod:`hybridcomp.monitor.transitions` — the monitor as pure transitions: a frozen state, one function per clock
* :mod:`hybridcomp.monitor.daemon` — :class:`Monitor` (the shell around the transitions) and :func:`run_monitor`
  (the asyncio loop)
* :mod:`hybridcomp.monitor.regeneration` — the background CD generation job
* :mod:`hybridcomp.monitor.state` — the daemon's state as one dataclass with a derived JSON form
* :mod:`hybridcomp.monitor.store` — the monitor's events and state in the CD database

The scenario harness that judges the daemon against a simulated real machine is :mod:`hybridcomp.scenario`
(beside the demo); drift metrics are in :mod:`hybridcomp.metrics`.
"""

from hybridcomp._lazy import lazy_exports
from hybridcomp._packages import refuse_top_level_import

refuse_top_level_import(__name__)  # hybridcomp.<package>, never the folder's own name

# module -> the public names it defines (imported on first use)
__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "config": ("ConfigError", "MonitorConfig", "example_config", "load_config", "parse_config"),
    "daemon": ("Monitor", "Regenerator", "RunResult", "run_monitor"),
    "sinks": ("MemorySink", "Offset", "make_sink"),
    "sources": ("ListSource", "Reading", "ReplaySource", "SourceFileError"),
})
