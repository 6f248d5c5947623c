"""Smoke tests of `twin bench`: each scenario runs briefly and prints every figure as JSON.

The figures themselves are not asserted (a benchmark measures, it does not pass or fail); docs/performance.md
has the full runs. These tests prove the scenarios run end to end against a real mosquitto and a real agent
process, and that the JSON keeps every field the docs describe.
"""

from __future__ import annotations

import importlib
import json
import os
import py_compile
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from conftest import copy_bundled_scene
from twin.bench.footprint import BYTECODE_PROBES, HEALTHZ_CALLS, bytecode_cached, model_config

pytestmark = pytest.mark.slow

LATENCY_FIELDS = {"count", "mean", "p50", "p99", "max"}
RUN_FIELDS = {
    "sent",
    "received",
    "lost",
    "sustained_rate",
    "cpu_percent",
    "host_cpu_percent",
    "rss_max_mb",
    "elapsed_s",
}


def bench_process(*args: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    """`twin bench <args> --json` run to its end, whatever it returned."""
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    return subprocess.run(
        [sys.executable, "-m", "twin.cli", "bench", *args, "--json"],
        check=False,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )


def bench(*args: str, timeout: float = 240) -> dict:
    proc = bench_process(*args, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout)


def test_throughput_reports_ceiling_agent_and_latencies() -> None:
    figures = bench("throughput", "--arms", "20", "--rate", "10", "--seconds", "2")
    assert figures["scenario"] == "throughput"
    assert {"arms", "rate_hz", "seconds", "offered_rate", "agent_to_ceiling_ratio"} <= set(figures)
    assert set(figures["ceiling"]) >= RUN_FIELDS
    agent = figures["agent"]
    assert RUN_FIELDS | {"applied", "mirrored_rate", "coalesced", "rejected", "devices_seen"} <= set(agent)
    assert set(agent["internal_latency_s"]) >= LATENCY_FIELDS
    assert set(agent["end_to_end_latency_s"]) >= LATENCY_FIELDS
    # The run really carried traffic through the agent (not a figure check: 400 messages were offered).
    assert agent["received"] > 0 and agent["applied"] > 0
    assert agent["devices_seen"] == 20
    assert agent["stop"]["exit_code"] == 0 and {"stop_s", "unwritten", "workers_killed"} <= set(agent["stop"])


def test_fidelity_compares_hold_and_prediction_at_both_jitters() -> None:
    figures = bench("fidelity", "--seconds", "5")
    assert figures["scenario"] == "fidelity"
    assert [case["jitter_ms"] for case in figures["cases"]] == [0.0, 50.0]
    for case in figures["cases"]:
        for estimator in ("hold_last_value", "predict"):
            assert {"mean_error_rad", "max_error_rad", "mean_error_deg", "max_error_deg", "frames"} <= set(
                case[estimator]
            )
            assert case[estimator]["frames"] > 0
        assert {"mean_error_ratio", "max_error_ratio"} <= set(case)


def test_footprint_reports_cold_start_and_memory() -> None:
    figures = bench("footprint", "--arms", "20", "--seconds", "2")
    assert figures["scenario"] == "footprint"
    assert {
        "cold_start_to_first_pose_s",
        "rss_idle_mb",
        "fleet_arms",
        "fleet_devices_mirrored",
        "rss_at_fleet_mb",
        "rss_peak_mb",
    } <= set(figures)
    assert figures["fleet_devices_mirrored"] == 20
    assert figures["cold_start_to_first_pose_s"] > 0
    # The agent and its workers, one figure each; the workers' fork server is reported on its own.
    assert figures["processes"] == 1 + (figures["workers"] if figures["workers"] > 1 else 0)
    assert (figures["rss_fork_server_mb"] is not None) == (figures["workers"] > 1)
    # /healthz answered while the fleet published (in its second half).
    assert 1 <= len(figures["healthz_ms_at_fleet"]) <= HEALTHZ_CALLS
    assert all(ms > 0 for ms in figures["healthz_ms_at_fleet"])
    # The installed libraries' bytecode is compiled by make setup (UV_COMPILE_BYTECODE), so the cold start
    # does not measure compiling them; the checkout's own modules are compiled as of the last make setup.
    cached = figures["bytecode_cached"]
    assert set(cached) == set(BYTECODE_PROBES)
    assert all(cached[name] for name in BYTECODE_PROBES if not name.startswith("twin.")), cached


def test_footprint_runs_the_agent_on_the_model_it_is_given(tmp_path: Path) -> None:
    scene = copy_bundled_scene(tmp_path)
    figures = bench("footprint", "--arms", "4", "--seconds", "1", "--model", str(scene))
    assert figures["model"] == str(scene.resolve())
    assert figures["fleet_devices_mirrored"] == 4
    # The agent really loads that file: one MuJoCo cannot parse stops it, and the bench says why.
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody>")
    proc = bench_process("footprint", "--arms", "4", "--seconds", "1", "--model", str(broken))
    assert proc.returncode == 1
    assert "the agent exited with code 2" in proc.stderr
    assert f"robot model {broken} could not be loaded by MuJoCo" in proc.stderr


def test_footprint_model_must_be_a_file(tmp_path: Path) -> None:
    missing = tmp_path / "no-scene.xml"
    proc = bench_process("footprint", "--model", str(missing))
    assert proc.returncode == 1
    assert f"--model {missing}: no such file" in proc.stderr
    assert proc.stdout == ""


def test_model_config_reads_back_as_the_absolute_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Quotes and backslashes in a directory name must not break the TOML the agent reads.
    odd = tmp_path / 'a "quoted" \\ dir'
    odd.mkdir()
    (odd / "scene.xml").write_text("<mujoco/>")
    monkeypatch.chdir(odd)
    text = model_config("scene.xml")
    assert tomllib.loads(text) == {"twin": {"model": str(odd / "scene.xml")}}
    assert model_config(None) == ""


def test_bytecode_counts_only_what_python_would_load(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    source = tmp_path / "probe_module.py"
    source.write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    assert bytecode_cached(["probe_module", "no_such_module_here"]) == {
        "probe_module": False,  # no __pycache__ file
        "no_such_module_here": False,
    }
    py_compile.compile(str(source))
    assert bytecode_cached(["probe_module"]) == {"probe_module": True}
    # An edited source: its old bytecode would be compiled again at each start, never used.
    source.write_text("X = 22\n")
    assert bytecode_cached(["probe_module"]) == {"probe_module": False}


def test_history_storage_reports_bytes_per_arm_day() -> None:
    figures = bench("history-storage", "--hours", "0.05")
    assert figures["scenario"] == "history-storage"
    assert figures["messages"] == 1800  # 3 simulated minutes at 10 Hz, all through the real writer
    fields = {"data_bytes", "files", "bytes_per_message", "mb_per_arm_day", "compact_s", "write_s"}
    assert fields <= set(figures)
    assert figures["files"] == 1 and figures["data_bytes"] > 0


def test_history_read_reports_one_devices_window_before_and_after_compaction() -> None:
    figures = bench("history-read", "--arms", "5", "--minutes", "1")
    assert figures["scenario"] == "history-read"
    assert figures["device_rows_read"] == 600 and figures["rows_match"] is True
    assert figures["files_before_compaction"] == 6 and figures["files_after_compaction"] == 1
    assert {"read_s_before_compaction", "read_s_after_compaction"} <= set(figures)


def test_history_load_compares_the_mirror_with_history_off_and_on() -> None:
    figures = bench("history-load", "--arms", "20", "--seconds", "2")
    assert figures["scenario"] == "history-load"
    assert {"mirrored_rate_on_over_off", "internal_p99_on_over_off", "table_bytes"} <= set(figures)
    assert figures["on"]["history"] is not None and figures["off"]["history"] is None
    # Every message the agent handed to history is a row once SIGTERM's final commit is done.
    assert figures["rows_written"] == figures["rows_handed_to_history"] > 0
    assert figures["rows_counted_unwritten"] == figures["rows_unaccounted"] == 0
    # The agent's stop: a clean exit, nothing it said it could not write.
    assert figures["on"]["stop"]["exit_code"] == 0
    assert figures["on"]["stop"]["unwritten"] == {} and figures["on"]["stop"]["workers_killed"] == []


def test_stop_figures_read_the_agent_stopped_line_of_the_agents_log(tmp_path: Path) -> None:
    """The benchmarks' `stop` figures come from the agent's own JSON log line; a log without one (everything
    written, logged at INFO below the run's WARNING) gives nothing unwritten."""
    import io
    import logging
    from types import SimpleNamespace
    from typing import Any, cast

    from twin.bench.harness import stop_figures
    from twin.service.logs import JsonLinesFormatter

    log_path = tmp_path / "agent-8080.log"
    rig = cast(Any, SimpleNamespace(agent_log=lambda port: log_path if port == "8080" else tmp_path / "none"))
    log_path.write_text("twin: starting\n")
    assert stop_figures(rig, "http://127.0.0.1:8080") == {"unwritten": {}, "workers_killed": []}
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonLinesFormatter())
    logger = logging.getLogger("test_bench.stop_figures")
    logger.addHandler(handler)
    try:
        logger.error(
            "agent stopped; not everything was written: 4 history_rows_unread",
            extra={"unwritten": {"history_rows_unread": 4}, "workers_killed": [1], "shutdown_budget_s": 60},
        )
    finally:
        logger.removeHandler(handler)
    log_path.write_text("twin: starting\n" + stream.getvalue())
    assert stop_figures(rig, "http://127.0.0.1:8080") == {
        "unwritten": {"history_rows_unread": 4},
        "workers_killed": [1],
    }


def test_ros2_reports_the_bridge_cost_and_that_samples_reached_a_reader() -> None:
    # Runs inside a loopback-only network namespace of its own (DDS discovery never leaves it).
    figures = bench("ros2", "--arms", "10", "--rate", "10", "--seconds", "2")
    assert figures["scenario"] == "ros2"
    assert {"bridge_cpu_percent", "mirrored_rate_ratio", "load_average", "offered_rate"} <= set(figures)
    for phase in ("without_bridge", "with_bridge"):
        assert RUN_FIELDS | {"applied", "mirrored_rate", "sinks"} <= set(figures[phase])
    assert [s["name"] for s in figures["without_bridge"]["sinks"]] == []
    sink = figures["ros2_sink"]
    assert sink["errors"] == 0, sink["last_error"]
    # The bridge really published, and a DDS reader really received (not a figure check).
    assert sink["delivered"] > 0
    assert 0 < figures["reader"]["received"] <= sink["delivered"]


def test_render_reports_frame_times_load_and_the_demo_pictures() -> None:
    figures = bench("render", "--frames", "3", "--width", "160", "--height", "120")
    assert figures["scenario"] == "render"
    assert {"gl_renderer", "model", "model_load_s", "frame_size", "frames", "target_frame_ms"} <= set(figures)
    assert {"demo_png_s", "demo_gif_30_frames_s", "load_average_1m"} <= set(figures)
    # The bundled model really was drawn with its part meshes, from both views.
    assert (figures["meshes"], figures["mesh_faces"], figures["frame_size"]) == (13, 44_582, "160x120")
    for view in ("framed", "overview"):
        for clock in ("wall_ms", "cpu_ms"):
            assert {"p50", "p90", "min"} <= set(figures["frame"][view][clock])
        assert figures["frame"][view]["wall_ms"]["p50"] > 0


def test_rerun_reports_the_agent_without_and_with_the_stream() -> None:
    figures = bench("rerun", "--arms", "5", "--seconds", "2")
    assert figures["scenario"] == "rerun"
    assert {"mirrored_rate_cost", "extra_cpu_percent_of_core", "load_average_1m", "offered_rate"} <= set(
        figures
    )
    for phase in ("off", "on"):
        assert {"sent", "received", "applied", "mirrored_rate", "cpu_percent", "rss_max_mb"} <= set(
            figures[phase]
        )
        assert figures[phase]["applied"] > 0
    assert figures["off"]["sink"] is None
    # The second run really streamed: the sink took every applied sample and wrote a recording.
    sink = figures["on"]["sink"]
    assert sink["delivered"] == figures["on"]["applied"] and sink["errors"] == 0
    assert figures["on"]["rrd_mb"] > 0


def test_quota_reports_each_phase_with_the_proxy_drops_and_the_estimate() -> None:
    out = bench("quota", "--arms", "20", "--rate", "10", "--seconds", "2", timeout=300)
    assert out["scenario"] == "quota" and out["budget_per_connection"] == 100
    phases = {p["phase"]: p for p in out["phases"]}
    assert set(phases) == {"one_connection", "pool_listed", "pool_fleet"}
    for phase in phases.values():
        assert phase.keys() >= {
            "sent",
            "proxy_dropped",
            "received",
            "applied",
            "estimated_lost",
            "estimate_error_of_sent",
            "connections",
            "internal_latency_s",
        }
        assert phase["received"] > 0
    # 20 arms at 10 Hz is 200 msg/s: one connection is over the budget, the listed pool uses three.
    assert phases["one_connection"]["connections"] == 1
    assert phases["pool_listed"]["connections"] == 3


def test_decode_compares_with_json_loads_in_one_run() -> None:
    out = bench("decode", timeout=120)
    assert [c["variant"] for c in out["cases"]] == ["ticks", "ticks", "degrees"]
    for case in out["cases"]:
        assert case["json_loads_us"] > 0 and case["decode_validate_us"] > 0
        assert case["ratio"] == case["decode_validate_us"] / case["json_loads_us"]


def test_usd_times_every_sample_it_records_against_json_loads() -> None:
    out = bench("usd", "--arms", "20", "--blocks", "3", timeout=120)
    assert out["samples_written"] == 60 and out["blocks_timed"] == 2
    figures = out["sample_in_json_loads"]
    assert 0 < figures["min"] <= figures["median"] <= figures["max"]
    assert out["sample_us"]["median"] > 0 and out["json_loads_us"]["median"] > 0


def test_worker_handles_every_message_and_prints_its_cost() -> None:
    out = bench("worker", "--arms", "50", "--rounds", "5", timeout=120)
    assert [c["alarms"] for c in out["cases"]] == [True, False]
    for case in out["cases"]:
        assert case["errors"] == 0
        assert case["first_message_us"] > 0 and case["message_us"] > 0


def test_worker_by_batch_size_reports_each_size_and_the_cost_of_a_batch() -> None:
    out = bench("worker", "--arms", "40", "--rounds", "2", "--batch", "4", "40", timeout=120)
    assert out["scenario"] == "worker-batches" and out["errors"] == 0
    assert [row["batch"] for row in out["sizes"]] == [4, 40]
    for row in out["sizes"]:
        assert row["message_us"] > 0 and row["json_loads_us"] > 0
        assert row["loads"] == pytest.approx(row["message_us"] / row["json_loads_us"])
    fit = out["fit"]
    # Two sizes: the line goes through both points.
    for row in out["sizes"]:
        batch_us = fit["per_batch_us"] + fit["per_message_us"] * row["batch"]
        assert batch_us == pytest.approx(row["message_us"] * row["batch"])
    refused = bench_process("worker", "--batch", "0")
    assert refused.returncode == 2 and "a batch holds at least 1 message, got 0" in refused.stderr


def test_console_reports_time_to_interactive_and_the_cpu_of_two_consoles() -> None:
    out = bench("console", "--arms", "20", "--cpu-arms", "10", "--runs", "2", "--seconds", "2", timeout=300)
    assert out["scenario"] == "console"
    interactive = out["interactive"]
    assert interactive["arms"] == 20 and interactive["runs"] == 2
    for figure in ("ready_ms", "search_ms", "update_ms"):
        spread = interactive[figure]
        assert 0 < spread["min"] <= spread["median"] <= spread["max"], figure
    cpu = out["cpu"]
    assert cpu["consoles"] == 2 and cpu["agent_cpu_percent_with"] > 0
    assert all(n >= 1 for n in cpu["updates_per_console"])
    assert cpu["agent_cpu_percent_with_arm_page"] > 0  # then one arm's page, open for as long
    # Then the viewer's stream of one arm, and the whole state's: each delivered frames while measured.
    assert cpu["viewer_frames_per_s"] > 0 and cpu["whole_state_stream_frames_per_s"] > 0
    assert "viewer_cpu_percent_cost" in cpu and "whole_state_stream_cpu_percent_cost" in cpu


def test_cost_reports_cpu_per_message_in_json_loads_and_by_stage() -> None:
    # Two workers asked for: by default the agent starts one per usable core, and on a host (or a CI
    # container, or taskset) with one core the mirror runs in the receiving process, whose workers' CPU is 0.
    out = bench("cost", "--arms", "20", "--seconds", "2", "--workers", "2", timeout=180)
    assert out["scenario"] == "cost"
    (size,) = out["sizes"]
    assert size["arms"] == 20 and size["summary"]["runs"] == 1
    (run,) = size["runs"]
    assert run["workers"] == 2
    # The run carried traffic, the probe measured the yardstick through it, and the CPU was split.
    assert run["received"] > 0 and run["mirrored"] > 0
    assert run["json_loads_us"]["samples"] > 0 and run["json_loads_us"]["median"] > 0
    assert run["loads_per_received"] > 0 and run["loads_per_mirrored"] > 0
    assert set(run["stages_loads_per_received"]) == set(out["stages"])
    # The workers decode and apply every message: CPU they must show. The receiving process's few tens of
    # ms over 2 s are spread over several threads, each read in whole 10 ms ticks (psutil), so on a fast
    # machine it can read 0; it is only required to be there.
    assert run["cpu_s"]["workers"] > 0 and run["cpu_s"]["receiving_process"] >= 0
    # The workers' stages are sampled: the output says so, and how many batches the estimate rests on (about
    # 1 in 16 of a few hundred batches: none timed would be odds of about 1e-11).
    assert "sampled" in out["stage_timing"]
    batches = run["worker_batches"]
    assert 0 < batches["stages_timed"] <= batches["handled"]
    # The split covers the whole: the stages add up to at least the agent's total (more only when the
    # sampled estimate of the workers' stages overshoots their measured CPU, which `other` cannot offset).
    stages = run["stages_loads_per_received"]
    assert all(v >= 0 for v in stages.values()), stages
    assert sum(stages.values()) >= run["loads_per_received"] * (1 - 1e-9)
    assert stages["decode"] > 0 and stages["health_alarms"] > 0
    assert 0 < run["alarm_evaluations"] <= run["mirrored"]
    assert {"before", "after"} <= set(run["load_average_1m"])


def test_cost_without_the_alarm_stage_runs_the_agent_with_alarms_off() -> None:
    out = bench("cost", "--arms", "20", "--seconds", "2", "--no-alarms", timeout=180)
    ((run,),) = [size["runs"] for size in out["sizes"]]
    assert run["alarms"] is False and run["received"] > 0 and run["mirrored"] > 0
    assert run["alarm_evaluations"] == 0, run["alarm_evaluations"]


def test_cost_counts_a_thread_under_a_reused_id_from_zero() -> None:
    # Thread ids wrap at the host's pid_max: a thread with less CPU than the one its id had before the
    # window is a new thread, and its CPU is all in the window (never a negative delta).
    from twin.bench.cost import _delta, _Threads

    before = _Threads(1, {10: ("twin-send-0", 2.0), 11: ("twin-crt", 0.5)})
    after = _Threads(1, {10: ("twin-http", 0.25), 11: ("twin-crt", 0.75), 12: ("twin-new", 0.125)})
    assert _delta(before, after) == {10: ("twin-http", 0.25), 11: ("twin-crt", 0.25), 12: ("twin-new", 0.125)}


def test_cost_split_never_reads_a_stage_below_zero() -> None:
    # The receiving process's threads: the event loop and a sender used CPU in the window, its other threads
    # none. 1.69 + 2.5 - 1.69 - 2.5 is -4.4e-16 in floating point; the split must give `other` exactly 0.
    from twin.bench.cost import STAGES, _split, _Threads

    before = {1: _Threads(1, {10: ("AwsEventLoop 1", 0.0), 11: ("twin-send-0", 0.0), 12: ("twin-http", 3.0)})}
    after = {1: _Threads(1, {10: ("AwsEventLoop 1", 1.69), 11: ("twin-send-0", 2.5), 12: ("twin-http", 3.0)})}
    roles, by_stage = _split(before, after, receiving=1, workers=(), history_pid=None, stages={})
    assert roles["receiving_process"] == 1.69 + 2.5
    assert by_stage == {**dict.fromkeys(STAGES, 0.0), "receive": 1.69, "hand_over": 2.5}
    assert all(v >= 0 for v in by_stage.values())
