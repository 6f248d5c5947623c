"""A worker's checkpoint, in one process: what crosses the control pipe, and a mirror started again from it.

The agent takes each worker's checkpoint every second and keeps it to start the worker again after a crash
(service.shards, `WorkerShard`); tests/test_restarts.py kills a real worker. Here the checkpoint of a mirror
fed the edge's mock fleet is pickled as the pipe pickles it, and a second mirror restores from the copy.
"""

from __future__ import annotations

import pickle
from multiprocessing import Pipe
from multiprocessing.connection import Connection

import pytest
from twin.bench.worker import _feed, _fleet
from twin.service.admission import DeviceBudget
from twin.service.config import load_config
from twin.service.mirror import Mirror, PipeInbox
from twin.service.shards import MirrorCheckpoint, MirrorReport, PackedDevices
from twin.transport.pipe import send_end

ARMS = 12


def _mirror(reader: Connection) -> Mirror:
    config = load_config(
        None, {"telemetry.devices": ["*"], "telemetry.units": "auto", "telemetry.max_devices": 64}
    )
    return Mirror(config, inbox=PipeInbox(reader), budget=DeviceBudget(64))


@pytest.fixture(scope="module")
def fed() -> tuple[MirrorReport, MirrorCheckpoint]:
    """A mirror fed 90 rounds of the mock fleet (units=auto decides each arm's): its report and checkpoint."""
    reader, writer = Pipe(duplex=False)
    mirror = _mirror(reader)
    mirror.start()
    try:
        rounds = _fleet(ARMS, 90)
        del rounds[40][3]  # one arm loses a message: its loss estimate has something to carry
        _feed(mirror, writer, rounds)
        return mirror.report(), mirror.checkpoint()
    finally:
        send_end(writer)
        mirror.stop(timeout=30.0)


def test_the_pipe_carries_the_devices_as_one_blob(fed: tuple[MirrorReport, MirrorCheckpoint]) -> None:
    _, checkpoint = fed
    assert isinstance(checkpoint.devices, PackedDevices)
    wire = pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL)
    copy = pickle.loads(wire)
    assert isinstance(copy.devices, PackedDevices)
    assert copy.devices.blob == checkpoint.devices.blob
    # Reading a device unpacks the blob; pickling again still carries the blob only.
    assert len(copy.devices) == ARMS
    assert pickle.dumps(copy, protocol=pickle.HIGHEST_PROTOCOL) == wire
    assert copy == checkpoint


def test_a_mirror_restored_from_the_copy_has_each_arms_counters_loss_units_and_pose(
    fed: tuple[MirrorReport, MirrorCheckpoint],
) -> None:
    report, checkpoint = fed
    copy = pickle.loads(pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL))
    restored = _mirror(Pipe(duplex=False)[0])  # never started: it restores on the calling thread
    assert restored.restore(copy).devices == ARMS
    after = restored.report()
    assert sorted(after.devices) == sorted(report.devices)
    lossy = [d for d in report.devices.values() if d.loss.lost]
    assert len(lossy) == 1 and lossy[0].loss.lost == 1
    for device, before in report.devices.items():
        now = after.devices[device]
        assert now.health.counters == before.health.counters
        assert now.health.counters.applied > 0
        assert now.units == before.units != "auto"
        assert now.timestamp_ms == before.timestamp_ms
        assert now.targets_rad == before.targets_rad
        assert (now.loss.lost, now.loss.received, now.loss.period_s) == (
            before.loss.lost,
            before.loss.received,
            before.loss.period_s,
        )
