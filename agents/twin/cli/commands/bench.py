"""`twin bench`: throughput, fidelity and footprint figures (docs/performance.md says how to read them)."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from twin.cli.output import Console, import_dev_tool

console = Console("bench")


def _fleet_load(
    parser: argparse.ArgumentParser, *, arms: int, seconds_help: str = "how long it publishes"
) -> None:
    # The offered load of the fleet scenarios: N arms at R Hz for S seconds.
    parser.add_argument("--arms", type=int, default=arms)
    parser.add_argument("--rate", type=float, default=10.0, help="messages per second per arm")
    parser.add_argument("--seconds", type=float, default=20.0, help=seconds_help)


# What `twin bench all --help` says of its exit status, which tells a complete run from a partial one.
ALL_EPILOG = """exit codes: 0 every step gave figures; 1 a step failed (the other steps' figures are printed
all the same); 2 bad command line; 3 none failed, but a step that cannot run here was skipped (no root
for ros2, no chromium for console: stderr names the fix); 130 interrupted (Ctrl-C): the figures of the steps
that finished are printed, with "interrupted": the step it stopped, and the plot is left as it was"""


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="measure the agent (throughput, fidelity, footprint, history, quota, sinks ...); print figures",
        description="Benchmarks print figures; they assert nothing. See docs/performance.md.",
    )
    sub = parser.add_subparsers(dest="scenario", metavar="SCENARIO", required=True)
    # In the order --help lists them.
    scenarios = [
        *_twin_scenarios(sub),
        *_history_scenarios(sub),
        *_part_scenarios(sub),
        *_long_scenarios(sub),
    ]
    for p in scenarios:
        p.add_argument("--json", action="store_true", help="print the figures as one JSON object")
        p.set_defaults(func=run)


def _twin_scenarios(sub: Any) -> list[argparse.ArgumentParser]:
    """The fleet through one agent, the twin's fidelity, and its start-up and memory."""
    tp = sub.add_parser("throughput", help="N arms at R Hz through a private mosquitto into one agent")
    _fleet_load(tp, arms=2000)

    fi = sub.add_parser("fidelity", help="twin pose at 60 Hz vs the true motion, hold-last-value vs ours")
    fi.add_argument("--seconds", type=float, default=60.0)

    fo = sub.add_parser("footprint", help="cold start to first pose; RSS idle and with a large fleet")
    fo.add_argument("--arms", type=int, default=1000)
    fo.add_argument("--seconds", type=float, default=8.0, help="how long the fleet publishes")
    fo.add_argument("--model", help="an MJCF scene for the agent's [twin] model (default: the bundled one)")
    return [tp, fi, fo]


def _history_scenarios(sub: Any) -> list[argparse.ArgumentParser]:
    """The telemetry history: its storage, reading it back, and its load on the mirror."""
    hs = sub.add_parser("history-storage", help="bytes one arm's day of history takes (edge mock, compacted)")
    hs.add_argument("--hours", type=float, default=24.0, help="simulated hours written (scaled to a day)")
    hs.add_argument("--variant", choices=["ticks", "degrees"], default="ticks")

    hr = sub.add_parser("history-read", help="one device's hour read back from a fleet's history table")
    hr.add_argument("--arms", type=int, default=100)
    hr.add_argument("--minutes", type=float, default=60.0)

    hl = sub.add_parser("history-load", help="the mirror with history off vs on; rows written vs received")
    _fleet_load(hl, arms=1000)
    return [hs, hr, hl]


def _batch_size(text: str) -> int:
    size = int(text)
    if size < 1:
        raise argparse.ArgumentTypeError(f"a batch holds at least 1 message, got {size}")
    return size


def _part_scenarios(sub: Any) -> list[argparse.ArgumentParser]:
    """One part's cost each: the sinks, rendering, the IoT Core quota, decoding, USD, a worker process."""
    r2 = sub.add_parser("ros2", help="the ROS 2 bridge's cost: the same fleet without and with it")
    _fleet_load(r2, arms=100)

    rn = sub.add_parser("render", help="offscreen frame time with the part meshes, model load, demo pictures")
    rn.add_argument("--frames", type=int, default=40, help="timed frames per view (after 5 warm-up frames)")
    rn.add_argument("--width", type=int, default=640)
    rn.add_argument("--height", type=int, default=480)

    rr = sub.add_parser("rerun", help="the agent without and with the [rerun] sink: mirrored rate and CPU")
    _fleet_load(rr, arms=100)

    qu = sub.add_parser(
        "quota", help="a fleet through an IoT-Core-like per-connection quota: one connection vs the pool"
    )
    _fleet_load(qu, arms=200, seconds_help="measured window of each phase")

    de = sub.add_parser("decode", help="decode + validate of an edge message against json.loads of it")

    us = sub.add_parser("usd", help="one USD recording sample (FK + record) against json.loads, per arm")
    us.add_argument("--arms", type=int, default=200)
    us.add_argument("--blocks", type=int, default=12, help="blocks of one sample per arm (the first untimed)")

    wo = sub.add_parser("worker", help="CPU per message of one worker process, fed through its pipe")
    wo.add_argument("--arms", type=int, default=1000)
    wo.add_argument("--rounds", type=int, default=40, help="messages per arm (10 Hz edge timestamps)")
    wo.add_argument(
        "--batch",
        type=_batch_size,
        nargs="+",
        metavar="N",
        help="instead: CPU per message at these batch sizes, the worker idle between batches (alarms on)",
    )
    return [r2, rn, rr, qu, de, us, wo]


def _long_scenarios(sub: Any) -> list[argparse.ArgumentParser]:
    """The scenarios with several options: the console, the cost per message, the soaks, and all of them."""
    cs = sub.add_parser(
        "console", help="the operator console: fleet page interactive at 2,000 arms, CPU of two consoles"
    )
    cs.add_argument("--arms", type=int, default=2000, help="arms on the fleet page timed to interactive")
    cs.add_argument("--cpu-arms", type=int, default=1000, help="arms while two consoles' CPU is measured")
    cs.add_argument("--rate", type=float, default=2.0, help="messages per second per arm")
    cs.add_argument("--runs", type=int, default=5, help="page loads timed")
    cs.add_argument("--seconds", type=float, default=20.0, help="CPU measurement window of each phase")

    co = sub.add_parser(
        "cost", help="the agent's CPU per message in units of json.loads of it, by stage, measured in one run"
    )
    co.add_argument("--arms", type=int, nargs="+", default=[100, 1000, 2000], help="fleet sizes, each a run")
    co.add_argument("--rate", type=float, default=10.0, help="messages per second per arm")
    co.add_argument("--seconds", type=float, default=20.0, help="how long each run publishes")
    co.add_argument("--runs", type=int, default=1, help="runs of each fleet size (summarised)")
    co.add_argument("--history", action="store_true", help="with the telemetry history on (a temp dir)")
    co.add_argument("--workers", type=int, default=None, help="the agent's --workers (default: its own)")
    co.add_argument(
        "--no-alarms",
        dest="alarms",
        action="store_false",
        help="with [alarms] enabled = false: what the agent costs without the servo alarm stage",
    )

    so = sub.add_parser(
        "soak", help="a fleet for minutes or hours with every sink on: RSS, files, disk, losses over time"
    )
    so.add_argument("--minutes", type=float, default=60.0)
    so.add_argument("--arms", type=int, default=200)
    so.add_argument("--rate", type=float, default=10.0, help="messages per second per arm")
    so.add_argument("--out", type=Path, default=Path("out/soak"), help="where soak.json and soak.png go")

    ch = sub.add_parser(
        "churn", help="a steady fleet plus arms that come and go, forgotten: RSS once the stores are full"
    )
    ch.add_argument("--minutes", type=float, default=40.0)
    ch.add_argument("--steady", type=int, default=200, help="arms publishing the whole run")
    ch.add_argument("--rate", type=float, default=5.0, help="messages per second per steady arm")
    ch.add_argument("--churn-per-min", type=int, default=500, help="new device ids a minute")
    ch.add_argument("--workers", type=int, default=2, help="the agent's --workers")
    ch.add_argument(
        "--events-capacity",
        type=int,
        default=None,
        help="the agent's [twin] events_capacity (default: its own)",
    )
    ch.add_argument("--sample-s", type=float, default=30.0, help="seconds between samples")
    ch.add_argument("--out", type=Path, default=Path("out/churn"), help="where churn.json goes")

    all_help = "every scenario as published in docs/performance.md, plus the plot"
    al = sub.add_parser(
        "all", help=all_help, epilog=ALL_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    al.add_argument("--seconds", type=float, default=20.0, help="throughput run length")
    al.add_argument("--plot", type=Path, default=Path("docs/performance.png"))
    return [cs, co, so, ch, al]


def _bench(scenario: str) -> ModuleType:
    # Development tooling: absent from the agent package deployed to the instance (DevToolMissing says so).
    return import_dev_tool(f"twin.bench.{scenario}", "bench")


def _figures(args: argparse.Namespace) -> dict[str, Any]:
    if args.scenario.startswith("history-"):
        history = _bench("history")
        if args.scenario == "history-storage":
            return history.storage(hours=args.hours, variant=args.variant)
        if args.scenario == "history-read":
            return history.read(arms=args.arms, minutes=args.minutes)
        return history.load(arms=args.arms, rate=args.rate, seconds=args.seconds)
    if args.scenario == "throughput":
        return _bench("throughput").run(arms=args.arms, rate=args.rate, seconds=args.seconds)
    if args.scenario == "fidelity":
        return _bench("fidelity").run(seconds=args.seconds)
    if args.scenario == "footprint":
        return _bench("footprint").run(fleet=args.arms, fleet_seconds=args.seconds, model=args.model)
    if args.scenario == "ros2":
        return _bench("ros2").run(arms=args.arms, rate=args.rate, seconds=args.seconds)
    if args.scenario == "render":
        return _bench("render").run(frames=args.frames, width=args.width, height=args.height)
    if args.scenario == "rerun":
        return _bench("rerun").run(arms=args.arms, rate=args.rate, seconds=args.seconds)
    if args.scenario == "quota":
        return _bench("quota").run(arms=args.arms, rate=args.rate, seconds=args.seconds)
    if args.scenario == "decode":
        return _bench("decode").run()
    if args.scenario == "usd":
        return _bench("usd").run(arms=args.arms, blocks=args.blocks)
    if args.scenario == "console":
        return _bench("console").run(
            arms=args.arms, cpu_arms=args.cpu_arms, rate=args.rate, runs=args.runs, seconds=args.seconds
        )
    if args.scenario == "soak":
        return _bench("soak").run(minutes=args.minutes, arms=args.arms, rate=args.rate, out=args.out)
    if args.scenario == "churn":
        return _churn(args)
    if args.scenario == "worker":
        return _bench("worker").run(arms=args.arms, rounds=args.rounds, batches=args.batch)
    if args.scenario == "cost":
        return _bench("cost").run(
            arms=args.arms,
            rate=args.rate,
            seconds=args.seconds,
            runs=args.runs,
            history=args.history,
            workers=args.workers,
            alarms=args.alarms,
        )
    return _every_scenario(args)


def _churn(args: argparse.Namespace) -> dict[str, Any]:
    churn = _bench("churn")
    settings = churn.Churn(
        minutes=args.minutes,
        steady=args.steady,
        rate=args.rate,
        churn_per_min=args.churn_per_min,
        workers=args.workers,
        sample_s=args.sample_s,
        **({"events_capacity": args.events_capacity} if args.events_capacity is not None else {}),
    )
    return churn.run(settings, out=args.out)


def _every_scenario(args: argparse.Namespace) -> dict[str, Any]:
    """`twin bench all`: the two throughput loads the targets name, fidelity, footprint, ROS 2, render, Rerun,
    the quota (one connection vs the pool), decode and a USD recording sample against json.loads, a worker's
    cost per message, and the agent's whole cost per message in json.loads units; then the plot of them."""
    throughput, seconds = _bench("throughput"), args.seconds
    steps: list[tuple[str, Callable[[], dict[str, Any]]]] = [
        ("throughput (100 arms)", lambda: throughput.run(arms=100, rate=10.0, seconds=seconds)),
        ("throughput (2000 arms)", lambda: throughput.run(arms=2000, rate=10.0, seconds=seconds)),
        ("fidelity", lambda: _bench("fidelity").run()),
        ("footprint", lambda: _bench("footprint").run()),
        ("ros2", lambda: _bench("ros2").run(arms=100, rate=10.0, seconds=seconds)),
        ("render", lambda: _bench("render").run()),
        ("rerun", lambda: _bench("rerun").run(arms=100, rate=10.0, seconds=seconds)),
        ("quota", lambda: _bench("quota").run(seconds=seconds)),
        ("decode", lambda: _bench("decode").run()),
        ("usd", lambda: _bench("usd").run()),
        ("worker", lambda: _bench("worker").run()),
        ("console", lambda: _bench("console").run(seconds=seconds)),
        ("cost", lambda: _bench("cost").run(seconds=seconds)),
    ]
    results = _run_steps(steps)
    if "interrupted" in results:  # the plot of a part of the run would replace the whole run's
        return results
    # The plot's latency panel is the two throughput runs: without one it would be drawn empty or half, and
    # replace the committed docs/performance.png with it, unnoticed.
    gave_none = {**results.get("skipped", {}), **results.get("failed", {})}
    lost = [name for name, _ in steps if name.startswith("throughput") and name in gave_none]
    if lost:
        results.setdefault("skipped", {})["plot"] = (
            f"not drawn, {args.plot} is left as it was: it needs the figures of {' and '.join(lost)}"
        )
        return results
    try:
        results["plot"] = str(_bench("plot").write(results, args.plot))
    except KeyboardInterrupt:  # every step's figures are in: printed, and the plot is left as it was
        results["interrupted"] = "plot"
    except Exception as exc:  # the figures are printed all the same; the run fails
        results.setdefault("failed", {})["plot"] = f"{type(exc).__name__}: {exc}"
    return results


# `twin bench all`'s exit codes beyond 0 (every step ran) and 1 (a step failed): steps skipped, none failed
# (ALL_EPILOG); interrupted, as a shell reports a command that SIGINT ended.
EXIT_SKIPPED = 3
EXIT_INTERRUPTED = 130


def _run_steps(steps: list[tuple[str, Callable[[], dict[str, Any]]]]) -> dict[str, Any]:
    """Every step's figures, in order. A step that cannot run here (twin.bench.unavailable) is skipped and one
    that raises anything else failed; either way the steps after it still run, so the figures of a long run
    are not lost to one, and `skipped` and `failed` (step name -> why) say which. Ctrl-C ends the run at
    that step, and `interrupted` names it: the figures so far are returned, not lost with the run."""
    unavailable = _bench("unavailable").Unavailable
    results: dict[str, Any] = {"throughput": []}
    skipped: dict[str, str] = {}
    failed: dict[str, str] = {}
    for n, (name, step) in enumerate(steps, 1):
        try:
            # Minutes with no output otherwise (more on a busy machine), and stdout is often a file: say where
            # it is, on stderr, so the figures stay as they were. Inside the try, as Ctrl-C on this line
            # between two steps lost every figure before it.
            console.err(f"{n} of {len(steps)}: {name}")
            figures = step()
        except KeyboardInterrupt:
            results["interrupted"] = name
            break
        except unavailable as exc:
            skipped[name] = str(exc)
            console.err(f"{name}: skipped, it cannot run here: {exc}")
            continue
        except Exception as exc:  # any error is the step's: reported, and the run goes on
            failed[name] = f"{type(exc).__name__}: {exc}"
            console.err(f"{name}: failed: {failed[name]}")
            continue
        if name.startswith("throughput"):
            results["throughput"].append(figures)
        else:
            results[name] = figures
    if skipped:
        results["skipped"] = skipped
    if failed:
        results["failed"] = failed
    return results


def _summary(figures: dict[str, Any]) -> int:
    """Say on stderr which steps of `bench all` did not give figures; the exit code that tells it."""
    skipped, failed = figures.get("skipped", {}), figures.get("failed", {})
    for name, why in skipped.items():
        console.err(f"skipped {name}: {why}")
    for name, why in failed.items():
        console.err(f"FAILED {name}: {why}")
    if failed or skipped:
        console.err(
            f"{len(failed)} step(s) failed, {len(skipped)} skipped: {', '.join([*failed, *skipped])}; "
            "the figures above are the other steps'"
        )
    if "interrupted" in figures:
        step = figures["interrupted"]
        # The plot comes after every step: all the figures are there, only the picture is not.
        done = "every step's, the plot not drawn" if step == "plot" else "the steps before it"
        console.err(f"interrupted during {step}: the figures above are {done}")
        return EXIT_INTERRUPTED
    return 1 if failed else EXIT_SKIPPED if skipped else 0


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _print_tree(data: Any, indent: str = "") -> None:
    if isinstance(data, dict):
        for key, value in data.items():
            if isinstance(value, dict | list):
                print(f"{indent}{key}:")
                _print_tree(value, indent + "  ")
            else:
                print(f"{indent}{key}: {_fmt(value)}")
    elif isinstance(data, list):
        for i, item in enumerate(data):
            print(f"{indent}[{i}]")
            _print_tree(item, indent + "  ")
    else:
        print(f"{indent}{_fmt(data)}")


def run(args: argparse.Namespace) -> int:
    try:
        figures = _figures(args)
    except RuntimeError as exc:  # DevToolMissing, or a scenario that could not run (says why)
        console.err(str(exc))
        return 1
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        _print_tree(figures)
    return _summary(figures) if args.scenario == "all" else 0
