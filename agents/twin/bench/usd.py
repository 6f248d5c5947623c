"""USD recording: what one recorded sample costs the recording sink's thread, in `json.loads` units.

The recording sink (twin.output.recording) runs on a thread of the agent's process, under the one interpreter
lock with the mirror, so every millisecond it takes is one the mirror waits for at a large fleet. This times
what the sink does per sample: forward kinematics (`RobotModel.body_poses`) and `SessionRecorder.record` of
the poses and six joints' servo readings, for `arms` arms in turn, a second apart on the session clock (so
no sample is dropped by the recorder's time-code rule). Blocks of it alternate with blocks of `json.loads`
of one edge message on the same thread (CPU time, `time.thread_time`), and each block's cost per sample is
divided by the `json.loads` time measured just before it: a machine that runs 2x slower for a minute moves
both. The first block, which adds the arms to the stage, is left out; saving the layer is not timed (the
sink saves every `record_flush_s`, not per sample).

    python -m twin.bench.usd [--arms 200] [--blocks 12]
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from twin.bench.harness import spread
from twin.core.telemetry import JointDiagnostics
from twin.edge.payload import encode, make_payload
from twin.output.recorder import SessionRecorder
from twin.robot import so101
from twin.robot.model import RobotModel

LOADS_PER_BLOCK = 4000


def _edge_message() -> bytes:
    """The edge's message as the throughput loads publish it (mock motion with servo diagnostics)."""
    return encode(make_payload("arm-0001", 1.0, "ticks", random.Random(1), timestamp_ms=1_706_000_000_000))


def run(arms: int = 200, blocks: int = 12) -> dict[str, Any]:
    """Per-sample cost of FK + record over `blocks` blocks of `arms` samples (median and spread)."""
    if arms < 1 or blocks < 2:
        raise ValueError(f"arms must be >= 1 and blocks >= 2, got arms={arms}, blocks={blocks}")
    robot = RobotModel.load(None)
    message = _edge_message()
    diagnostics = {
        joint: JointDiagnostics(
            velocity_rad_s=0.1, load_percent=5.0, temperature_c=35.0, current_a=0.1, voltage_v=12.0
        )
        for joint in so101.JOINT_NAMES
    }
    devices = [f"arm-{i:04d}" for i in range(arms)]
    ratios: list[float] = []
    sample_us: list[float] = []
    loads_us: list[float] = []
    with tempfile.TemporaryDirectory(prefix="twin-bench-usd-") as tmp:
        recorder = SessionRecorder(Path(tmp) / "session.usdc", flush_interval_s=3600.0)
        try:
            for block in range(blocks):
                start = time.thread_time()
                for _ in range(LOADS_PER_BLOCK):
                    json.loads(message)
                loads = (time.thread_time() - start) / LOADS_PER_BLOCK
                start = time.thread_time()
                for k, device in enumerate(devices):
                    # A different pose per arm and block, within the joint ranges: no sample repeats the last.
                    angle = 0.1 * ((k + block) % 7) - 0.3
                    poses = robot.body_poses(dict.fromkeys(so101.JOINT_NAMES, angle))
                    recorder.record(device, float(block), poses, diagnostics)
                per = (time.thread_time() - start) / arms
                if block == 0:
                    continue  # adds the arms to the stage: a one-off per session, not a sample's cost
                ratios.append(per / loads)
                sample_us.append(per * 1e6)
                loads_us.append(loads * 1e6)
            written = recorder.samples_written
        finally:
            recorder.close()
    if written != arms * blocks:
        raise RuntimeError(
            f"the recorder wrote {written} of {arms * blocks} samples; the figures would mislead"
        )
    return {
        "scenario": "usd",
        "arms": arms,
        "blocks_timed": len(ratios),
        "samples_written": written,
        "sample_in_json_loads": spread(ratios),
        "sample_us": spread(sample_us),
        "json_loads_us": spread(loads_us),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--arms", type=int, default=200)
    parser.add_argument("--blocks", type=int, default=12)
    args = parser.parse_args(argv)
    sys.stdout.write(json.dumps(run(arms=args.arms, blocks=args.blocks)) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
