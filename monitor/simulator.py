"""A machine control simulator: an OPC UA server (asyncua) that plays a trace CSV.

It exposes one Double variable per trace column (node ids ``ns=<idx>;s=<column>``
in the namespace ``urn:hybridcomp:machine``, e.g. ``ns=2;s=time_s``) and three
writable offset variables ``dx_um``, ``dy_um``, ``dz_um`` for the monitor's OPC UA
sink. Per trace row it writes every column, then ``time_s``. Used by the tests
and for demos::

    python -m hybridcomp.monitor.simulator --trace trace.csv --port 4840 --speed 100
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
import signal
import sys
from pathlib import Path

from hybridcomp.models.layout import DRIFT_COLUMNS

log = logging.getLogger(__name__)

NAMESPACE = "urn:hybridcomp:machine"
OFFSETS = DRIFT_COLUMNS


def node_ids(columns, ns: int = 2) -> dict[str, str]:
    """Trace column -> node id string of the simulator (``ns=2;s=time_s``)."""
    return {c: f"ns={ns};s={c}" for c in columns}


async def serve_trace(trace: Path, port: int, speed: float = 1.0, start_s: float = -math.inf,
                      stop: asyncio.Event | None = None, loop_forever: bool = True) -> None:
    """Serve the trace on ``opc.tcp://127.0.0.1:port`` and play it at ``speed`` (machine s per wall s).

    After the last row the values stay (``loop_forever``) until ``stop`` is set.
    """
    from hybridcomp.monitor.sources import _asyncua

    aua = _asyncua()
    ua = aua.ua
    stop = stop or asyncio.Event()
    with open(trace) as fh:
        header = fh.readline().strip().split(",")
    server = aua.Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/")
    server.set_server_name("hybridcomp machine simulator")
    idx = await server.register_namespace(NAMESPACE)
    obj = await server.nodes.objects.add_object(ua.NodeId("machine", idx), "machine")
    nodes = {}
    for c in header:
        nodes[c] = await obj.add_variable(ua.NodeId(c, idx), c, ua.Variant(0.0, ua.VariantType.Double))
    for c in OFFSETS:
        v = await obj.add_variable(ua.NodeId(c, idx), c, ua.Variant(0.0, ua.VariantType.Double))
        await v.set_writable()
        nodes[c] = v
    async with server:
        log.info("serving %s on port %d (namespace %d)", trace, port, idx)
        print(f"ready {port}", flush=True)
        loop = asyncio.get_running_loop()
        t0 = w0 = None
        with open(trace) as fh:
            fh.readline()
            for line in fh:
                if stop.is_set():
                    break
                f = line.rstrip("\n").split(",")
                vals = [float(x) if x.strip() else math.nan for x in f]
                t = vals[header.index("time_s")]
                if t <= start_s:
                    continue
                if t0 is None:
                    t0, w0 = t, loop.time()
                if speed > 0:
                    wait = w0 + (t - t0) / speed - loop.time()
                    if wait > 0:
                        await asyncio.sleep(wait)
                for c, v in zip(header, vals):
                    if c != "time_s":
                        await server.write_attribute_value(nodes[c].nodeid, ua.DataValue(ua.Variant(v, ua.VariantType.Double)))
                await server.write_attribute_value(nodes["time_s"].nodeid, ua.DataValue(ua.Variant(t, ua.VariantType.Double)))
        print("done", flush=True)
        if loop_forever:
            await stop.wait()


def main(argv=None) -> int:
    """The simulator's command line (see the module docstring); returns the exit code."""
    p = argparse.ArgumentParser(prog="python -m hybridcomp.monitor.simulator", description=__doc__.split("\n\n")[0])
    p.add_argument("--trace", required=True, type=Path, help="trace CSV to play")
    p.add_argument("--port", type=int, default=4840, help="TCP port on 127.0.0.1 (default 4840)")
    p.add_argument("--speed", type=float, default=1.0, help="machine seconds per wall second (0: as fast as possible)")
    p.add_argument("--start-s", type=float, default=-math.inf, help="skip rows up to this machine time [s]")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)

    async def run():
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await serve_trace(args.trace, args.port, args.speed, args.start_s, stop)

    asyncio.run(run())
    return 0


if __name__ == "__main__":
    sys.exit(main())
