"""Monitor configuration, replay parsing, drift metrics, regeneration loads, metrics text, CLI wiring."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridcomp.metrics import drift_metrics, window_ranges
from hybridcomp.monitor.config import (
    ConfigError,
    example_config,
    load_config,
    parse_config,
)
from hybridcomp.monitor.regeneration import RegenerationRequest, request_loads
from hybridcomp.monitor.sources import SourceFileError, read_replay
from hybridcomp.scenario import fit_mlr, predict_mlr

BASE = {"monitor": {"machine": "vmc800", "database": "cd.db", "rom": "r.npz"}, "source": {"path": "t.csv"},
        "sink": {"path": "o.jsonl"}}


def cfg(**sections):
    data = {k: dict(v) for k, v in BASE.items()}
    for k, v in sections.items():
        data.setdefault(k, {}).update(v)
    return parse_config(data, "m.toml")


def test_example_config_parses_with_the_documented_defaults(tmp_path):
    p = tmp_path / "monitor.toml"
    p.write_text(example_config())
    c = load_config(p)
    assert (c.compensation_interval_s, c.monitoring_interval_s, c.threshold_K) == (5.0, 900.0, 0.5)
    assert c.database == str(tmp_path / "cds.sqlite") and c.source.path == tmp_path / "jobshop_trace.csv"
    assert c.source.speed == 0.0  # the walk-through replays as fast as it can; speed = 1 is real time
    assert c.regeneration.job == "hybridcomp.monitor.regeneration:default_job"


@pytest.mark.parametrize("section,key,hint", [
    ("monitor", "treshold_K", "threshold_K"),
    ("compensation", "max_ofset_um", "max_offset_um"),
    ("sensors", "hold", "hold_s"),
    ("source", "sped", "speed"),
])
def test_a_misspelt_key_is_an_error_with_a_hint(section, key, hint):
    with pytest.raises(ConfigError, match=rf"m\.toml: field '{section}\.{key}' is not a known field \(did you mean '{hint}'\?\)"):
        cfg(**{section: {key: 1.0}})


def test_unknown_section_and_bad_values():
    with pytest.raises(ConfigError, match=r"unknown section \[sensor\] \(did you mean 'sensors'\?\)"):
        parse_config({**BASE, "sensor": {}}, "m.toml")
    with pytest.raises(ConfigError, match="field 'monitor.threshold_K' must be positive, got -1"):
        cfg(monitor={"threshold_K": -1})
    with pytest.raises(ConfigError, match="must be a number, got True"):
        cfg(monitor={"threshold_K": True})
    with pytest.raises(ConfigError, match="whole multiple of monitor.increment_s"):
        cfg(monitor={"monitoring_interval_s": 1010})  # 50.5 model steps of 20 s
    with pytest.raises(ConfigError, match="field 'source.kind' is 'mqtt', must be one of replay, opcua"):
        cfg(source={"kind": "mqtt"})
    with pytest.raises(ConfigError, match="source.nodes.time_s is missing"):
        cfg(source={"kind": "opcua", "url": "opc.tcp://127.0.0.1:4840", "nodes": {"x_mm": "ns=2;s=x"}})
    with pytest.raises(ConfigError, match="regeneration.job 'nojob' must be 'module:function'"):
        cfg(regeneration={"job": "nojob"})
    with pytest.raises(ConfigError, match="sink.nodes.dq_um is not an offset"):
        cfg(sink={"kind": "opcua", "url": "opc.tcp://x", "nodes": {"dq_um": "ns=2;s=a"}})
    # the fail-safe limit on a set's predicted error: a positive number, at least hard_um
    assert cfg().validity.reject_um == 50.0 and cfg(validity={"reject_um": 3}).validity.reject_um == 3.0
    with pytest.raises(ConfigError, match=r"m\.toml: \[validity\] reject_um must be at least hard_um \(3\), got 2"):
        cfg(validity={"reject_um": 2})
    with pytest.raises(ConfigError, match=r"^m\.toml: field 'validity\.reject_um' must not be negative, got -5"):
        cfg(validity={"reject_um": -5})
    with pytest.raises(ConfigError, match="field 'validity.reject_um' must be a number, got 'x'"):
        cfg(validity={"reject_um": "x"})
    with pytest.raises(ConfigError, match="monitor.rom is missing"):
        parse_config({"monitor": {"machine": "vmc800", "database": "x"}, "source": {"path": "t"}, "sink": {"path": "o"}},
                     "m.toml")


def test_database_url_passes_through_and_paths_are_relative_to_the_file(tmp_path):
    c = parse_config({**BASE, "monitor": {**BASE["monitor"], "database": "postgresql+psycopg://u@h/db"}}, "m.toml", tmp_path)
    assert c.database == "postgresql+psycopg://u@h/db" and c.rom == tmp_path / "r.npz"


# --------------------------------------------------------------------------- replay parsing


def test_replay_reads_sensors_and_nan(machine, tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("time_s,x_mm,y_mm,z_mm,spindle_rpm,T1_degC,T8_degC,Tamb_degC,dz_um\n"
                 "0,1,2,3,100,20.5,,19.0,4\n1,1.5,2,3,100,NaN,20.1,19.1,4\n")
    r = list(read_replay(p, machine))
    assert r[0].position_mm == (1.0, 2.0, 3.0) and r[0].sensors_degC["T1"] == 20.5 and math.isnan(r[0].sensors_degC["T8"])
    assert math.isnan(r[1].sensors_degC["T1"]) and r[1].air_degC == {"Tamb_degC": 19.1}


def test_replay_errors_name_file_line_and_column(machine, tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("time_s,x_mm,y_mm,z_mm,T9_degC\n")
    with pytest.raises(SourceFileError, match=r"t\.csv: line 1: unknown column 'T9_degC'"):
        list(read_replay(p, machine))
    p.write_text("time_s,x_mm,y_mm,z_mm\n0,1,2,3\n1,1,abc,3\n")
    with pytest.raises(SourceFileError, match=r"t\.csv: line 3: column 'y_mm' is not a number: 'abc'"):
        list(read_replay(p, machine))
    p.write_text("time_s,x_mm,y_mm\n")
    with pytest.raises(SourceFileError, match="column 'z_mm' \\(axis Z\\) is missing"):
        list(read_replay(p, machine))


# --------------------------------------------------------------------------- drift metrics


def test_drift_metrics_of_exact_signals():
    t = np.arange(0.0, 16 * 3600.0 + 1, 60.0)
    A = 3.0
    sine = A * np.sin(2 * np.pi * t / 3600.0)  # whole periods: RMS A/√2, P2P 2A
    ramp = 1e-3 * t  # 1 µm per 1000 s: every window's range is exactly slope × window
    R = np.column_stack([sine, ramp, np.zeros_like(t)])
    m = drift_metrics(t, R, windows_s=(900.0, 3600.0, 15 * 3600.0))
    assert m["dx_um"]["rms_um"] == pytest.approx(A / math.sqrt(2), rel=1e-3)
    assert m["dx_um"]["p2p_um"] == pytest.approx(2 * A, rel=1e-6)
    assert m["dx_um"]["p95_range_um"][3600.0] == pytest.approx(2 * A, rel=1e-6)  # a full period in every window
    assert m["dy_um"]["p95_range_um"][900.0] == pytest.approx(0.9)
    assert m["dy_um"]["p95_range_um"][15 * 3600.0] == pytest.approx(54.0)
    assert m["dz_um"]["rms_um"] == 0.0
    assert m["3d"]["rms_um"] == pytest.approx(math.sqrt(np.mean(sine**2 + ramp**2)))


def test_window_ranges_count_and_values():
    r = window_ranges(np.array([0.0, 1.0, 0.0, 5.0, 5.0]), 3)
    assert r.tolist() == [1.0, 5.0, 5.0]


def test_mlr_recovers_a_planted_linear_law():
    rng = np.random.default_rng(3)
    T = 20 + rng.normal(size=(200, 8))
    D = np.column_stack([1.0 + 2.0 * T[:, 0] - 0.5 * T[:, 7], -3.0 * T[:, 2], 0.7 * T[:, 4] + T[:, 5]])
    c = fit_mlr(T, D)
    assert predict_mlr(c, T) == pytest.approx(D, abs=1e-9)
    assert c[1, 0] == pytest.approx(2.0) and c[8, 0] == pytest.approx(-0.5)


# --------------------------------------------------------------------------- regeneration loads


def test_request_loads_keep_each_increments_heat():
    names = ["a_W", "ws_degC"]
    req = RegenerationRequest(
        machine="vmc800", pose_key="X=0", pose_mm={}, database="db", machine_time_s=900.0, t_reference_degC={},
        signature=None, rom="rom.npz", observer={}, observer_x=[], history_time_s=[], history_degC=[],
        history_drift_um=[], loads_names=names, loads_time_s=[300.0, 600.0, 900.0],
        loads_inputs=[[10.0, 1.0], [20.0, 2.0], [0.0, -1.0]], anchor_degC={}, anchor_um={}, forecast_h=3.0,
        bump_um=1.0, reference_temperature_degC=20.0, element_size_mm=80.0)
    L = request_loads(req, dt_s=60.0)
    assert L.time_s[0] == 0.0 and L.time_s[-1] == 900.0 and np.allclose(np.diff(L.time_s), 60.0)
    # piecewise constant: a grid time in increment (t_k-1, t_k] holds that increment's mean (the start holds the first)
    want = np.where(L.time_s <= 300.0, 10.0, np.where(L.time_s <= 600.0, 20.0, 0.0))
    assert L.values[:, 0].tolist() == want.tolist()
    assert L.values[L.time_s == 600.0, 1] == pytest.approx(22.0)  # air back in °C: 2 K over 20 °C
    with pytest.raises(ValueError, match="unknown field"):
        RegenerationRequest.from_dict({**req.to_dict(), "bogus": 1})


# --------------------------------------------------------------------------- metrics text and CLI


def metric_samples(text: str) -> dict:
    """{(sample name, sorted labels): value} of a Prometheus exposition text, read by the client's own parser."""
    from prometheus_client.parser import text_string_to_metric_families

    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for fam in text_string_to_metric_families(text) for s in fam.samples}


def test_prometheus_text():
    pytest.importorskip("prometheus_client", reason="the metrics need prometheus_client (extra live, in the test extra)")
    from prometheus_client.parser import text_string_to_metric_families

    from hybridcomp.monitor.metrics import metrics_text

    txt = metrics_text({"last_time_s": 900.0, "last_delta_T_K": 0.25, "offsets_um": {"dz_um": -3.5}, "readings": 10,
                        "degraded": ["T1"], "regeneration_running": False, "max_decision_s": 0.01,
                        "last_error_um": {"interval_um": 0.7, "forecast_um": math.inf}})
    s = metric_samples(txt)
    assert s[("hybridcomp_monitor_delta_t_kelvin", ())] == 0.25
    assert s[("hybridcomp_monitor_offset_micrometers", (("axis", "dz"),))] == -3.5
    assert ("hybridcomp_monitor_offset_micrometers", (("axis", "dx"),)) not in s  # an offset it has not: no sample
    assert s[("hybridcomp_monitor_predicted_error_micrometers", (("horizon", "interval"),))] == 0.7
    assert ("hybridcomp_monitor_predicted_error_micrometers", (("horizon", "forecast"),)) not in s  # inf: none
    assert s[("hybridcomp_monitor_readings_total", ())] == 10
    assert s[("hybridcomp_monitor_degraded_sensors", ())] == 1
    assert s[("hybridcomp_monitor_decision_seconds_max", ())] == 0.01
    assert s[("hybridcomp_monitor_regeneration_running", ())] == 0
    assert s[("hybridcomp_monitor_machine_time_seconds", ())] == 900.0
    assert ("hybridcomp_monitor_switches_total", ()) not in s  # a counter the status has not: none
    types = {f.name: f.type for f in text_string_to_metric_families(txt)}
    assert types["hybridcomp_monitor_readings"] == "counter" and types["hybridcomp_monitor_delta_t_kelvin"] == "gauge"


def test_prometheus_port_refused_without_the_client(monkeypatch, capsys, tmp_path):
    import asyncio
    import sys

    from hybridcomp.cli import main
    from hybridcomp.monitor.metrics import MetricsUnavailable, serve_metrics

    monkeypatch.setitem(sys.modules, "prometheus_client", None)  # import prometheus_client raises ImportError
    with pytest.raises(MetricsUnavailable, match=r'prometheus_port = 9109 needs prometheus_client.*pip install -e "\.\[live\]"'):
        asyncio.run(serve_metrics(object(), 9109))
    assert main(["monitor", "example-config", "--out", str(tmp_path / "m.toml")]) == 0
    text = (tmp_path / "m.toml").read_text()
    assert "prometheus_port = 0 " in text
    (tmp_path / "m.toml").write_text(text.replace("prometheus_port = 0 ", "prometheus_port = 9109 "))
    capsys.readouterr()
    assert main(["monitor", "run", "--config", str(tmp_path / "m.toml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {tmp_path / 'm.toml'}: [monitor] prometheus_port = 9109 needs prometheus_client")
    assert 'pip install -e ".[live]"' in err


def test_cli_help_and_example_config(capsys, tmp_path):
    from hybridcomp.cli import main

    with pytest.raises(SystemExit):
        main(["monitor", "--help"])
    assert "structure model" in capsys.readouterr().out
    assert main(["monitor", "example-config", "--out", str(tmp_path / "m.toml")]) == 0
    assert load_config(tmp_path / "m.toml").machine == "vmc800"
    (tmp_path / "bad.toml").write_text("[monitor]\nmachine='vmc800'\n")
    assert main(["monitor", "run", "--config", str(tmp_path / "bad.toml")]) == 2
    assert "monitor.database is missing" in capsys.readouterr().err


def test_metrics_endpoint_serves_the_status_on_localhost():
    import asyncio

    pytest.importorskip("prometheus_client", reason="the metrics need prometheus_client (extra live, in the test extra)")

    from hybridcomp.monitor.metrics import serve_metrics

    class Stub:
        def status(self):
            return {"last_time_s": 1800.0, "switches": 2}

    async def main():
        server = await serve_metrics(Stub(), 0)
        port = server.sockets[0].getsockname()[1]
        assert server.sockets[0].getsockname()[0] == "127.0.0.1"
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
        await writer.drain()
        body = await reader.read()
        writer.close()
        await writer.wait_closed()
        server.close()
        await server.wait_closed()
        return body.decode()

    text = asyncio.run(main())
    head, _, body = text.partition("\r\n\r\n")
    assert head.startswith("HTTP/1.1 200 OK") and "Content-Type: text/plain; version=" in head
    s = metric_samples(body)
    assert s[("hybridcomp_monitor_switches_total", ())] == 2
    assert s[("hybridcomp_monitor_machine_time_seconds", ())] == 1800.0


def test_example_trace_needs_a_readable_structure_model(capsys, tmp_path):
    from hybridcomp.cli import main

    out = tmp_path / "jobshop_trace.csv"
    assert main(["monitor", "example-trace", "--rom", str(tmp_path / "none.rom.npz"), "--out", str(out)]) == 2
    assert "none.rom.npz" in capsys.readouterr().err and not out.exists()
    with pytest.raises(SystemExit):
        main(["monitor", "example-trace", "--help"])
    assert "jobshop_trace.csv" in capsys.readouterr().out
