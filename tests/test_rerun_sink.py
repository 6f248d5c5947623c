"""The Rerun sink's .rrd, read back with Rerun's own dataframe API (a local rr.server.Server).

Telemetry goes through the real decoder into the sink; what comes back is checked against oracles that do not
use the code under test: forward kinematics straight from MuJoCo for the body transforms, and the payload's
own numbers converted by hand (the units in docs/telemetry.md) for the scalar series.
"""

from __future__ import annotations

import itertools
import json
import math
import time
from collections.abc import Iterator
from multiprocessing import Pipe
from pathlib import Path

import msgspec
import mujoco
import numpy as np
import pyarrow as pa
import pytest
from conftest import read_rrd, wait_for
from twin.core.alarms import AlarmThresholds, ServoAlarms
from twin.core.health import DeviceStatus
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.output import rerun_sink
from twin.output.rerun_settings import RerunSettings, RerunSettingsError
from twin.output.rerun_sink import RerunSink, status_text
from twin.output.sinks import AppliedSample, RejectedSample, StatusChange
from twin.robot import so101
from twin.robot.model import RobotModel, default_model_path
from twin.robot.visuals import fit_face_budget, visual_geoms
from twin.service.admission import DeviceBudget
from twin.service.config import load_config
from twin.service.events import FleetWatch
from twin.service.mirror import Mirror, PipeInbox
from twin.transport.pipe import Batch

T0_MS = 1_706_000_000_000
SAMPLES = 24
DEVICES = ("arm-001", "arm-002")
SPACING = 0.6
JAW_LO, JAW_HI = so101.JOINT_RANGES_RAD["gripper"]


def payload(device: str, i: int) -> dict:
    """LeRobot degrees (variant B): arm joints in degrees, gripper 0..100 %, servo fields in raw units."""
    d = int(device.rsplit("-", 1)[1]) - 1  # arm-001 is 0: each arm its own phase
    joints = {}
    for k, name in enumerate(so101.ARM_JOINTS):
        lo, hi = (math.degrees(v) for v in so101.JOINT_RANGES_RAD[name])
        joints[name] = {
            "position": round(0.8 * (lo + (hi - lo) * (0.5 + 0.45 * math.sin(0.3 * i + k + d))), 3)
        }
    joints["gripper"] = {"position": round(50 + 40 * math.sin(0.2 * i + d), 3)}
    for k, name in enumerate(so101.JOINT_NAMES):
        entry = joints[name]
        entry.update({"temp": 30 + k + i % 3, "load": 5 * k + i, "velocity": -3 * k + i, "voltage": 120 + k})
        if name != "wrist_roll":  # one joint without a current reading: a gap in that series
            entry["current"] = 40 + 2 * k + i
        # elbow_flex reports an overload (status bit 5) for samples 8..15.
        entry["status"] = 32 if name == "elbow_flex" and 8 <= i < 16 else 0
    return {"device_id": device, "timestamp": T0_MS + 100 * i, "joints": joints}


def hand_angles_rad(doc: dict) -> dict[str, float]:
    """Variant B by hand: degrees -> radians; gripper % onto the model's jaw range."""
    out = {n: math.radians(doc["joints"][n]["position"]) for n in so101.ARM_JOINTS}
    out["gripper"] = JAW_LO + doc["joints"]["gripper"]["position"] / 100.0 * (JAW_HI - JAW_LO)
    return out


def hand_servo(doc: dict, quantity: str) -> list[float]:
    """Servo fields by hand (docs/telemetry.md): load 0.1 %, current 6.5 mA (0.0065 A), voltage 0.1 V per
    unit, velocity in steps/s of 2 pi / 4096 rad."""
    scale = {
        "temperature_c": ("temp", 1.0),
        "load_percent": ("load", 0.1),
        "current_a": ("current", 0.0065),
        "velocity_rad_s": ("velocity", 2 * math.pi / 4096),
        "voltage_v": ("voltage", 0.1),
    }[quantity]
    key, factor = scale
    return [
        doc["joints"][n][key] * factor if key in doc["joints"][n] else math.nan for n in so101.JOINT_NAMES
    ]


def mujoco_fk(model: mujoco.MjModel, data: mujoco.MjData, angles: dict[str, float]) -> dict[str, tuple]:
    data.qpos[:] = model.qpos0
    for name, value in angles.items():
        data.qpos[model.joint(name).qposadr[0]] = value
    mujoco.mj_kinematics(model, data)
    return {
        b: (data.xpos[model.body(b).id].copy(), data.xquat[model.body(b).id].copy()) for b in so101.BODY_NAMES
    }


def feed(sink: RerunSink, *, period_s: float = 0.1, pause_every: int = 0) -> list[dict]:
    """Every sample of every device through the real decoder into the sink; `pause_every` samples the feed
    waits past the sink's flush delay, so the recording holds several batches per device."""
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    docs = []
    mono = time.monotonic()
    for i in range(SAMPLES):
        if pause_every and i and i % pause_every == 0:
            # Past the flush delay: the next sample finds the batch due, however late this thread runs.
            time.sleep(0.2)
        for device in DEVICES:
            doc = payload(device, i)
            docs.append(doc)
            telemetry = decoder.decode(json.dumps(doc), topic_device=device)
            sample = AppliedSample(
                device, time.time(), mono + i * period_s, telemetry, dict(telemetry.angles_rad)
            )
            sink.applied(sample)
    return docs


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


@pytest.fixture(scope="module")
def recording(
    robot: RobotModel, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[Path, list[dict], RerunSink]]:
    path = tmp_path_factory.mktemp("rerun") / "twin.rrd"
    sink = RerunSink(robot, RerunSettings(save=str(path), flush_s=0.05, fleet_spacing_m=SPACING))
    docs = feed(sink, pause_every=5)
    sink.rejected(
        RejectedSample("arm-002", "dt/lerobot/arm-002/telemetry", time.time(), "not_json", "bad", b"{")
    )
    sink.close()
    yield path, docs, sink


@pytest.fixture(scope="module")
def tables(recording) -> tuple[pa.Table, pa.Table]:
    return read_rrd(recording[0])


def entities(table: pa.Table) -> set[str]:
    return {name.split(":", 1)[0] for name in table.schema.names if name.startswith("/")}


def column(table: pa.Table, entity: str, component: str) -> list:
    return table.column(f"{entity}:{component}").to_pylist()


def times_ms(table: pa.Table) -> list[int]:
    return (table.column("edge_time").cast(pa.int64()).to_numpy() // 1_000_000).tolist()


def test_the_sink_delivered_every_sample(recording) -> None:
    path, docs, sink = recording
    stats = sink.stats()
    assert (stats.delivered, stats.dropped, stats.errors, stats.skipped) == (len(docs), 0, 0, 0), stats
    # Several batches per device, so the read-back checks cover batches after the first.
    assert sink.worker.batches_sent >= 3 * len(DEVICES)
    assert path.stat().st_size > 0


def test_entity_paths(robot: RobotModel, tables) -> None:
    temporal, static = tables
    # What the sink logs: the model's visual geoms thinned to the per-arm face budget (the official meshes
    # are over it).
    geoms, _ = fit_face_budget(visual_geoms(robot.model, robot.body_ids), RerunSettings().mesh_faces_per_arm)
    for device in DEVICES:
        arm = f"/arms/{device}"
        moving = {f"{arm}/{b}" for b in so101.BODY_NAMES if b != "base"}
        servo = {
            f"{arm}/servo/{q}"
            for q in ("temperature_c", "load_percent", "current_a", "velocity_rad_s", "voltage_v")
        }
        assert moving | servo | {f"{arm}/joints/angle_deg", f"{arm}/events"} <= entities(temporal)
        visuals = {f"{arm}/{g.body}/visual/{g.name}" for g in geoms}
        assert visuals | {arm, f"{arm}/base"} <= entities(static)
        # Each visual geom is a posed mesh with the model's colour.
        for g in geoms:
            entity = f"{arm}/{g.body}/visual/{g.name}"
            (positions,) = column(static, entity, "Mesh3D:vertex_positions")
            np.testing.assert_allclose(np.array(positions), g.vertices, atol=1e-7)
            (rgba,) = column(static, entity, "Mesh3D:albedo_factor")
            expected = [round(255 * c) for c in g.rgba]
            assert rgba[0] == int.from_bytes(bytes(expected), "big")
    # The second arm stands one grid step beside the first (along +y: each arm reaches along +x).
    (offset,) = column(static, "/arms/arm-002", "Transform3D:translation")
    np.testing.assert_allclose(offset[0], [0.0, SPACING, 0.0])
    (up,) = column(static, "/arms", "ViewCoordinates:xyz")
    assert up is not None


def test_arms_beyond_the_detailed_ones_get_the_far_meshes(robot: RobotModel, tmp_path: Path) -> None:
    # One detailed arm by position (the first), the focus arm detailed wherever it stands, the rest far.
    path = tmp_path / "far.rrd"
    settings = RerunSettings(
        save=str(path), mesh_detailed_arms=1, mesh_faces_far=5_000, focus_device="arm-003", flush_s=0.05
    )
    sink = RerunSink(robot, settings)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    for device in ("arm-001", "arm-002", "arm-003"):
        telemetry = decoder.decode(
            json.dumps(payload("arm-001", 0) | {"device_id": device}), topic_device=device
        )
        sink.applied(
            AppliedSample(device, time.time(), time.monotonic(), telemetry, dict(telemetry.angles_rad))
        )
    sink.close()
    near, _ = fit_face_budget(visual_geoms(robot.model, robot.body_ids), settings.mesh_faces_per_arm)
    far, _ = fit_face_budget(near, settings.mesh_faces_far)
    assert sum(g.face_count for g in far) <= settings.mesh_faces_far < sum(g.face_count for g in near)
    _, static = read_rrd(path)
    for device, geoms in (("arm-001", near), ("arm-002", far), ("arm-003", near)):
        for g in geoms:
            entity = f"/arms/{device}/{g.body}/visual/{g.name}"
            (positions,) = column(static, entity, "Mesh3D:vertex_positions")
            np.testing.assert_allclose(np.array(positions), g.vertices, atol=1e-7)
            (faces,) = column(static, entity, "Mesh3D:triangle_indices")
            assert len(faces) == g.face_count, (device, g.name)


def rows_of(table: pa.Table, entity: str, component: str) -> dict[int, object]:
    """edge_time (ms) -> the entity's value, over the rows that hold one (the reader may give several rows
    one time when different entities' chunks share it)."""
    out: dict[int, object] = {}
    for ts, value in zip(times_ms(table), column(table, entity, component), strict=True):
        if value is not None:
            assert ts not in out, f"{entity} has two values at {ts}"
            out[ts] = value
    return out


def test_transforms_at_sample_times_equal_mujoco_forward_kinematics(tables, recording) -> None:
    temporal, static = tables
    _, docs, _ = recording
    model = mujoco.MjModel.from_xml_path(str(default_model_path()))
    data = mujoco.MjData(model)
    checked = 0
    for device in DEVICES:
        arm = f"/arms/{device}"
        samples = {d["timestamp"]: d for d in docs if d["device_id"] == device}
        poses = {
            body: (
                rows_of(temporal, f"{arm}/{body}", "Transform3D:translation"),
                rows_of(temporal, f"{arm}/{body}", "Transform3D:quaternion"),
            )
            for body in so101.BODY_NAMES
            if body != "base"
        }
        # The base is welded to the world: logged once, statically.
        (base_pos,), (base_quat,) = (
            column(static, f"{arm}/base", "Transform3D:translation"),
            column(static, f"{arm}/base", "Transform3D:quaternion"),
        )
        for ts, doc in samples.items():
            expected = mujoco_fk(model, data, hand_angles_rad(doc))
            for body in so101.BODY_NAMES:
                if body == "base":
                    pos, quat = base_pos[0], base_quat[0]
                else:
                    pos, quat = poses[body][0][ts][0], poses[body][1][ts][0]
                want_pos, want_quat = expected[body]
                np.testing.assert_allclose(pos, want_pos, atol=2e-6)
                xyzw = np.array([*want_quat[1:], want_quat[0]])
                got = np.array(quat)
                assert min(np.abs(got - xyzw).max(), np.abs(got + xyzw).max()) < 2e-6, (device, ts, body)
            checked += 1
        # Nothing but the samples: one transform per body per sample time.
        for translations, quaternions in poses.values():
            assert set(translations) == set(quaternions) == set(samples)
    assert checked == SAMPLES * len(DEVICES)


def test_scalar_series_match_the_telemetry(tables, recording) -> None:
    temporal, _ = tables
    _, docs, _ = recording
    checked = 0
    for device in DEVICES:
        arm = f"/arms/{device}"
        samples = {d["timestamp"]: d for d in docs if d["device_id"] == device}
        angles = rows_of(temporal, f"{arm}/joints/angle_deg", "Scalars:scalars")
        servo = {
            q: rows_of(temporal, f"{arm}/servo/{q}", "Scalars:scalars")
            for q in ("temperature_c", "load_percent", "current_a", "velocity_rad_s", "voltage_v")
        }
        assert set(angles) == set(samples)
        for ts, doc in samples.items():
            want = hand_angles_rad(doc)
            np.testing.assert_allclose(
                angles[ts], [math.degrees(want[n]) for n in so101.JOINT_NAMES], atol=1e-9
            )
            # Arm joints in degrees are the payload's own numbers.
            np.testing.assert_allclose(
                angles[ts][:5], [doc["joints"][n]["position"] for n in so101.ARM_JOINTS], atol=1e-9
            )
            for quantity, values in servo.items():
                np.testing.assert_allclose(values[ts], hand_servo(doc, quantity), atol=1e-9, equal_nan=True)
            checked += 1
    assert checked == SAMPLES * len(DEVICES)


def test_status_and_rejections_are_events(tables) -> None:
    temporal, _ = tables
    text = [t for t in column(temporal, "/arms/arm-001/events", "TextLog:text") if t]
    flat = [line for cell in text for line in cell]
    assert flat == ["servo status: elbow_flex: overload error", "servo status: all servos report no error"]
    rejected = [
        line for cell in column(temporal, "/arms/arm-002/events", "TextLog:text") if cell for line in cell
    ]
    assert any(line.startswith("rejected (not_json): bad") for line in rejected)


def test_servo_alarms_raised_and_cleared_are_events(robot: RobotModel, tmp_path: Path) -> None:
    # The real alarm engine sees elbow_flex run hot, then cool; the events it returns ride on the samples.
    # (Its status bits, which these payloads also send, are left out: the temperature's two changes are all.)
    alarms = ServoAlarms(AlarmThresholds(latch=False, servo_error_bits=()))
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    path = tmp_path / "alarms.rrd"
    sink = RerunSink(robot, RerunSettings(save=str(path), flush_s=0.05))
    raised_at = cleared_at = None
    for i in range(SAMPLES * 2):
        telemetry = decoder.decode(json.dumps(payload("arm-001", i)), topic_device="arm-001")
        hot = 4 <= i < 30
        temp = 75.0 if hot else 35.0
        diagnostics = {
            j: msgspec.structs.replace(d, temperature_c=temp) for j, d in telemetry.diagnostics.items()
        }
        events = tuple(alarms.evaluate("arm-001", {"elbow_flex": diagnostics["elbow_flex"]}, {}, i * 1.0))
        if any(e.action == "raised" for e in events):
            raised_at = raised_at or telemetry.timestamp_ms
        if any(e.action == "cleared" for e in events):
            cleared_at = cleared_at or telemetry.timestamp_ms
        sample = AppliedSample(
            "arm-001", time.time(), i * 1.0, telemetry, dict(telemetry.angles_rad), alarm_events=events
        )
        sink.applied(sample)
    sink.close()
    assert raised_at and cleared_at, "the engine raised and cleared nothing: the test fed it nothing to see"
    temporal, _ = read_rrd(path)
    lines = [
        (t, line)
        for t, cell in zip(
            times_ms(temporal), column(temporal, "/arms/arm-001/events", "TextLog:text"), strict=True
        )
        if cell
        for line in cell
        if line.startswith("servo alarm")
    ]
    assert [line.split(":")[0] for _, line in lines] == ["servo alarm raised", "servo alarm cleared"]
    assert "elbow_flex" in lines[0][1]
    # On the edge-time timeline at the message that caused each change.
    assert [t for t, _ in lines] == [raised_at, cleared_at]


def test_after_an_edge_clock_reset_the_live_end_shows_the_newest_pose(
    robot: RobotModel, tmp_path: Path
) -> None:
    """A walk: an edge whose clock jumped back 30 s (rebooted without NTP, so the mirror rebuilt its twin) was
    logged 30 s behind its own earlier samples, and a viewer at the live end showed the pose from before the
    reset until the clock caught up. Its samples now follow its last one, in the order they were applied; once
    its clock is set right again (the last quarter), they are back at the edge's own time."""
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    path = tmp_path / "reset.rrd"
    sink = RerunSink(robot, RerunSettings(save=str(path), flush_s=0.05))
    docs = [payload("arm-001", i) for i in range(SAMPLES)]
    for doc in docs[SAMPLES // 2 : 3 * SAMPLES // 4]:
        doc["timestamp"] -= 30_000
    for i, doc in enumerate(docs):
        telemetry = decoder.decode(json.dumps(doc), topic_device="arm-001")
        sink.applied(AppliedSample("arm-001", time.time(), i * 0.1, telemetry, dict(telemetry.angles_rad)))
    sink.close()
    temporal, _ = read_rrd(path)
    series = column(temporal, "/arms/arm-001/joints/angle_deg", "Scalars:scalars")
    rows = sorted((t, a) for t, a in zip(times_ms(temporal), series, strict=True) if a)
    assert len(rows) == SAMPLES
    for (_, logged), doc in zip(rows, docs, strict=True):
        by_hand = hand_angles_rad(doc)
        assert logged == pytest.approx([math.degrees(by_hand[j]) for j in so101.JOINT_NAMES], abs=1e-6)
    # Before the reset each sample is at the edge's own time; after it, the 100 ms the agent received it
    # after the last one (the time that passed), then at the edge's spacing.
    assert [t for t, _ in rows[: SAMPLES // 2]] == [d["timestamp"] for d in docs[: SAMPLES // 2]]
    after_reset = [t for t, _ in rows[SAMPLES // 2 - 1 : 3 * SAMPLES // 4]]
    assert {b - a for a, b in itertools.pairwise(after_reset)} == {100}, after_reset
    assert [t for t, _ in rows[3 * SAMPLES // 4 :]] == [d["timestamp"] for d in docs[3 * SAMPLES // 4 :]]


class _Clock:
    def __init__(self, t: float) -> None:
        self.now = t

    def __call__(self) -> float:
        return self.now


class _Walk:
    """A real mirror on an injected clock with the Rerun sink, its worker's loop turned by the test: a batch
    of one sample of arm-001 (while it sends), then a status sweep, every 0.1 s."""

    def __init__(self, robot: RobotModel, path: Path) -> None:
        self.config = load_config(None, {"telemetry.devices": ["*"], "telemetry.units": "degrees"})
        self.clock = clock = _Clock(1000.0)
        self.mirror = Mirror(
            self.config,
            inbox=PipeInbox(Pipe(duplex=False)[0]),
            budget=DeviceBudget(4),
            clock=clock,
            wall_clock=lambda: T0_MS / 1000 + clock.now,
            sinks=[RerunSink(robot, RerunSettings(save=str(path), flush_s=0.05))],
        )
        self.mirror._open_sinks()  # the sinks without the worker thread: the test turns its loop
        self.step = 0
        self.sent: list[int] = []

    def run(self, seconds: float, *, sending: bool, lag: int = 0) -> None:
        """`lag`: the samples sent are that many steps older than the clock (delivered late)."""
        mirror, clock = self.mirror, self.clock
        for _ in range(round(seconds * 10)):
            self.step += 1
            clock.now = 1000.0 + self.step / 10
            if sending:
                doc = payload("arm-001", self.step - lag)
                self.sent.append(doc["timestamp"])
                topic = telemetry_topic(DEFAULT_TOPIC_PREFIX, "arm-001")
                batch = Batch(("arm-001",), (topic,), (json.dumps(doc).encode(),), (clock.now,), (clock(),))
                mirror._handle(batch, 0)
            mirror._watch_statuses((clock.now,) if sending else ())


def test_an_arm_going_stale_offline_and_back_is_told_at_the_live_end(
    robot: RobotModel, tmp_path: Path
) -> None:
    """A walk: an arm that went quiet kept its last pose in the viewer with no sign, while the console said
    STALE, then OFFLINE. A real mirror on an injected clock, as its worker drives it (a batch, then a status
    sweep, every 0.1 s), hands each change to the sink, which logs it on the arm's line after its last
    sample: where a viewer at the live end, which shows that sample's pose, sees it."""
    path = tmp_path / "status.rrd"
    walk = _Walk(robot, path)
    health, mirror, sent = walk.config.health, walk.mirror, walk.sent
    walk.run(1.0, sending=True)
    last_before = sent[-1]
    walk.run(health.offline_after_s + 1.0, sending=False)
    assert mirror.statuses()["arm-001"] is DeviceStatus.OFFLINE
    walk.run(1.0, sending=True)
    mirror.stop()
    temporal, _ = read_rrd(path)
    cells = zip(times_ms(temporal), column(temporal, "/arms/arm-001/events", "TextLog:text"), strict=True)
    # (The payloads' overload bits make servo lines too: the status lines are those of the arm.)
    lines = [(t, line) for t, cell in cells if cell for line in cell if line.startswith("arm ")]
    assert [line for _, line in lines] == [
        "arm STALE (was ONLINE): its pose is the last one it sent",
        "arm OFFLINE (was STALE): its pose is the last one it sent",
        "arm ONLINE (was OFFLINE)",
    ]
    (stale, _), (offline, _), (online, _) = lines
    # On the arm's line as long after its last sample as the mirror's sweep read the change (a sweep every
    # WATCH_INTERVAL_S, so within one of the thresholds), and the return at its first sample back.
    sweep_ms = FleetWatch.interval_s * 1000 + 100
    assert 0 < stale - last_before - health.stale_after_s * 1000 <= sweep_ms
    assert 0 <= offline - last_before - health.offline_after_s * 1000 <= sweep_ms
    first_back = sent[len(sent) // 2]
    assert offline < first_back <= online <= first_back + sweep_ms
    # Over the arm in the fleet view, a point labelled with its status, at the same times; cleared with the
    # return, as the console says it.
    labels = rows_of(temporal, "/arms/arm-001/status", "Points3D:labels")
    assert labels == {stale: ["STALE"], offline: ["OFFLINE"], online: []}


def test_an_arm_forgotten_while_offline_is_labelled_forgotten_at_the_forget(
    robot: RobotModel, tmp_path: Path
) -> None:
    """A walk: the agent forgot an arm OFFLINE that long and told no sink, so the red OFFLINE label stayed
    over it, and an arm of that name that published again was new to the mirror. The sink is told of the
    forget: its meshes stay drawn with the last pose, so a grey FORGOTTEN label says so (cleared, they read
    as an idle live arm), with a line that says why; the arm that publishes again is a new one, unlabelled
    from its first sample."""
    path = tmp_path / "forgotten.rrd"
    walk = _Walk(robot, path)
    walk.run(1.0, sending=True)
    walk.run(walk.config.health.offline_after_s + 1.0, sending=False)
    walk.mirror.forget_arm("arm-001")
    back = len(walk.sent)
    walk.run(1.0, sending=True)
    assert walk.mirror.statuses()["arm-001"] is DeviceStatus.ONLINE
    walk.mirror.stop()
    temporal, _ = read_rrd(path)
    labels = rows_of(temporal, "/arms/arm-001/status", "Points3D:labels")
    assert list(labels.values()) == [["STALE"], ["OFFLINE"], ["FORGOTTEN"], []]
    colours = rows_of(temporal, "/arms/arm-001/status", "Points3D:colors")
    forgotten_at, cleared_at = sorted(labels)[-2:]
    assert colours[forgotten_at] == [0x8C8C8CFF]  # grey: not live
    cells = zip(times_ms(temporal), column(temporal, "/arms/arm-001/events", "TextLog:text"), strict=True)
    lines = [(t, line) for t, cell in cells if cell for line in cell if line.startswith("arm ")]
    at, last = lines[-1]
    assert last == "arm forgotten by the agent (was OFFLINE)"
    assert at == forgotten_at < walk.sent[back] == cleared_at


def test_a_forget_that_overtakes_the_sweep_says_the_arm_was_offline(
    robot: RobotModel, tmp_path: Path
) -> None:
    """A review: the forget line said `(was STALE)` for an arm the mirror read OFFLINE, when the forget came
    before the sweep that would have told the sink. It says what the mirror read."""
    path = tmp_path / "overtaken.rrd"
    walk = _Walk(robot, path)
    health = walk.config.health
    walk.run(1.0, sending=True)
    walk.run(health.stale_after_s + 1.0, sending=False)
    assert walk.mirror.statuses()["arm-001"] is DeviceStatus.STALE
    walk.clock.now += health.offline_after_s  # no sweep in between: the sink was last told STALE
    walk.mirror.forget_arm("arm-001")
    walk.mirror.stop()
    temporal, _ = read_rrd(path)
    cells = column(temporal, "/arms/arm-001/events", "TextLog:text")
    lines = [line for cell in cells if cell for line in cell if line.startswith("arm ")]
    assert lines[-2:] == [
        "arm STALE (was ONLINE): its pose is the last one it sent",
        "arm forgotten by the agent (was OFFLINE)",
    ]


def test_the_arms_the_agent_forgets_leave_no_record_in_the_sink(
    robot: RobotModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The sink kept a record of every device id it ever drew: bounded by the arms tracked at once, but not
    by arms coming and going for weeks. A forget drops the arm's record, and keeps the time of its label
    for the newest FORGOTTEN_KEPT ids only."""
    monkeypatch.setattr(rerun_sink, "FORGOTTEN_KEPT", 5)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    sink = RerunSink(robot, RerunSettings(save=str(tmp_path / "churn.rrd"), flush_s=0.05))
    for n in range(20):
        device = f"arm-{n:03d}"
        telemetry = decoder.decode(json.dumps(payload(device, n)), topic_device=device)
        sink.applied(AppliedSample(device, time.time(), n * 1.0, telemetry, dict(telemetry.angles_rad)))
        gone = DeviceStatus.OFFLINE
        if n < 19:
            sink.status(StatusChange(device, gone, gone, at_mono_s=n + 0.5, at_wall_s=n, forgotten=True))
    wait_for(lambda: sink.stats().pending == 0, 30, "the sink to take every item")
    sink.close()
    arms = sink.worker._arms
    # The one left stands in a place of its own: a forgotten arm's meshes stay in theirs in the recording.
    assert list(arms) == ["arm-019"] and arms["arm-019"].index == 19
    assert list(sink.worker._forgotten.times) == [f"arm-{n:03d}" for n in range(14, 19)]


@pytest.mark.parametrize(
    "agent_behind_s", [0.0, 365 * 86_400.0], ids=["agent-clock-right", "agent-clock-behind"]
)
def test_an_arm_of_an_id_forgotten_too_long_ago_to_be_kept_still_clears_its_label(
    robot: RobotModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, agent_behind_s: float
) -> None:
    """A review: once an id dropped out of the FORGOTTEN_KEPT kept, an arm of that id came back onto its
    entity path under the grey label, never cleared. Once any id is dropped, every new arm clears the label,
    after the latest one dropped. A second review: with the agent's clock a year behind (a board before NTP
    syncs) and the edges right, every dropped time read as ahead (FLOOR_AHEAD_TOLERANCE_S), the floor never
    moved and the label stayed; the forget's own label time outvotes the agent's clock."""
    monkeypatch.setattr(rerun_sink, "FORGOTTEN_KEPT", 2)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    path = tmp_path / "floor.rrd"
    sink = RerunSink(robot, RerunSettings(save=str(path), flush_s=0.05))
    gone = DeviceStatus.OFFLINE
    wall0 = T0_MS / 1000 - agent_behind_s  # the agent's clock; the edges' are right
    for n, device in enumerate(["arm-000", "arm-001", "arm-002", "arm-000"]):
        telemetry = decoder.decode(json.dumps(payload(device, n)), topic_device=device)
        sink.applied(AppliedSample(device, wall0 + n, n * 1.0, telemetry, dict(telemetry.angles_rad)))
        if n < 3:  # arm-000's time is dropped with arm-002's forget
            at = n + 0.5
            sink.status(StatusChange(device, gone, gone, at_mono_s=at, at_wall_s=wall0 + at, forgotten=True))
    wait_for(lambda: sink.stats().pending == 0, 30, "the sink to take every item")
    sink.close()
    assert "arm-000" not in sink.worker._forgotten.times
    assert sink.worker.floor_ahead_ignored == 0
    temporal, _ = read_rrd(path)
    labels = rows_of(temporal, "/arms/arm-000/status", "Points3D:labels")
    assert list(labels.values()) == [["FORGOTTEN"], []]
    # After its label: the only time dropped, arm-000's own, is the floor.
    forgotten_at, cleared_at = sorted(labels)
    assert cleared_at > forgotten_at


def _forgets_after_one_clock_ahead(robot: RobotModel, path: Path, ahead_ms: int) -> RerunSink:
    """arm-000's clock `ahead_ms` ahead of the agent's and the other arms': its FORGOTTEN label time is
    dropped (FORGOTTEN_KEPT 1) with arm-001's forget; then arm-002 goes STALE and OFFLINE, and arm-003 is
    forgotten at once. Returns the closed sink, its .rrd at `path`."""
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    sink = RerunSink(robot, RerunSettings(save=str(path), flush_s=0.05))
    gone, stale = DeviceStatus.OFFLINE, DeviceStatus.STALE
    wall0 = T0_MS / 1000  # the agent's clock, as the sound edges'
    for n, device in enumerate(["arm-000", "arm-001", "arm-002", "arm-003"]):
        doc = payload(device, n)
        if device == "arm-000":
            doc["timestamp"] += ahead_ms
        telemetry = decoder.decode(json.dumps(doc), topic_device=device)
        sink.applied(AppliedSample(device, wall0 + n, n * 1.0, telemetry, dict(telemetry.angles_rad)))
        if n != 2:  # arm-000's time is dropped with arm-001's forget; arm-003 is forgotten at once
            at = n + 0.5
            sink.status(StatusChange(device, gone, gone, at_mono_s=at, at_wall_s=wall0 + at, forgotten=True))
    sink.status(StatusChange("arm-002", DeviceStatus.ONLINE, stale, at_mono_s=3.0, at_wall_s=wall0 + 3.0))
    sink.status(StatusChange("arm-002", stale, gone, at_mono_s=4.0, at_wall_s=wall0 + 4.0))
    wait_for(lambda: sink.stats().pending == 0, 30, "the sink to take every item")
    sink.close()
    return sink


def test_a_new_arms_labels_go_after_its_clear_when_the_floor_is_ahead(
    robot: RobotModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A review: the floor of dropped label times comes from other arms' clocks, and one ahead put every new
    arm's first Clear there: its STALE and OFFLINE labels, at its own times, lost to that Clear at the live
    end. A label goes after its arm's last Clear (here a clock ahead by less than FLOOR_AHEAD_TOLERANCE_S,
    which moves the floor)."""
    monkeypatch.setattr(rerun_sink, "FORGOTTEN_KEPT", 1)
    path = tmp_path / "ahead.rrd"
    ahead_ms = int(rerun_sink.FLOOR_AHEAD_TOLERANCE_S * 1000) // 2
    sink = _forgets_after_one_clock_ahead(robot, path, ahead_ms)
    assert sink.worker.floor_ahead_ignored == 0
    temporal, _ = read_rrd(path)
    labels = rows_of(temporal, "/arms/arm-002/status", "Points3D:labels")
    # The Clear first, past the floor; the labels after it, in order: OFFLINE shows at the live end.
    assert [labels[t] for t in sorted(labels)] == [[], ["STALE"], ["OFFLINE"]], labels
    assert min(labels) > T0_MS + ahead_ms
    labels = rows_of(temporal, "/arms/arm-003/status", "Points3D:labels")
    assert [labels[t] for t in sorted(labels)] == [[], ["FORGOTTEN"]], labels


def test_an_edge_clock_far_ahead_does_not_move_later_arms_on_the_timeline(
    robot: RobotModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A walk: one arm's clock set to 2099 made the floor of dropped label times 2099, so every later arm's
    first Clear and its labels went there, 73 years from its samples on the timeline. A dropped time further
    ahead of the agent's clock than FLOOR_AHEAD_TOLERANCE_S leaves the floor where it was, counted and
    logged: later arms are labelled at their own times."""
    monkeypatch.setattr(rerun_sink, "FORGOTTEN_KEPT", 1)
    path = tmp_path / "far.rrd"
    far_ms = int(np.datetime64("2099-06-01", "ms").astype(np.int64))
    sink = _forgets_after_one_clock_ahead(robot, path, far_ms - T0_MS)
    assert sink.worker.floor_ahead_ignored == 1
    assert [r.getMessage() for r in caplog.records if "ahead of the agent's clock" in r.getMessage()]
    temporal, _ = read_rrd(path)
    labels = rows_of(temporal, "/arms/arm-002/status", "Points3D:labels")
    # No label inherited, so no Clear: its own labels, within seconds of its samples.
    assert [labels[t] for t in sorted(labels)] == [["STALE"], ["OFFLINE"]], labels
    assert max(labels) < T0_MS + 10_000
    labels = rows_of(temporal, "/arms/arm-003/status", "Points3D:labels")
    assert list(labels.values()) == [["FORGOTTEN"]] and max(labels) < T0_MS + 10_000
    # The arm whose clock was ahead keeps its own label at its own time.
    assert rows_of(temporal, "/arms/arm-000/status", "Points3D:labels") == {far_ms + 500: ["FORGOTTEN"]}


def test_forgetting_the_focus_arm_sends_no_layout_and_its_id_takes_its_place_back(
    robot: RobotModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A review: each forget of the focus arm handed the focus on and sent a layout, and every blueprint the
    SDK (0.41) builds keeps a stream and two threads for good: arms churning leaked threads for weeks. The
    focus stays on the forgotten arm (labelled FORGOTTEN), the layout goes once, and an arm of the focus id
    that comes back takes its place, where the layout's camera looks."""
    sent: list[object] = []
    send_blueprint = rerun_sink._Tee.send_blueprint
    monkeypatch.setattr(
        rerun_sink._Tee, "send_blueprint", lambda tee, *a, **k: (sent.append(a), send_blueprint(tee, *a, **k))
    )
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    sink = RerunSink(robot, RerunSettings(save=str(tmp_path / "focus.rrd"), flush_s=0.05))
    gone = DeviceStatus.OFFLINE

    def send(device: str, n: int) -> None:
        telemetry = decoder.decode(json.dumps(payload(device, n)), topic_device=device)
        sink.applied(AppliedSample(device, time.time(), n * 1.0, telemetry, dict(telemetry.angles_rad)))

    send("arm-000", 0)
    send("arm-001", 1)
    for n in range(2, 22, 2):  # the focus arm forgotten and back, ten times
        sink.status(StatusChange("arm-000", gone, gone, at_mono_s=n + 0.5, at_wall_s=n, forgotten=True))
        send("arm-000", n + 1)
    wait_for(lambda: sink.stats().pending == 0, 30, "the sink to take every item")
    sink.close()
    assert len(sent) == 1
    arms = sink.worker._arms
    assert sink.worker._focus == "arm-000" and arms["arm-000"].index == 0 and arms["arm-001"].index == 1


def test_a_lone_sample_of_a_stale_arm_writes_no_return_the_mirror_did_not_read(
    robot: RobotModel, tmp_path: Path
) -> None:
    """A review: the first sample back wrote `arm ONLINE (was STALE)`, but the mirror reads a status from
    silence: a STALE arm that sends one sample and falls quiet again stays STALE to it (and on the console),
    and no change to ONLINE comes. Its lines are the mirror's changes only, and so is its label: the lone
    sample cleared it while the console still said STALE, until the change to OFFLINE."""
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    path = tmp_path / "lone.rrd"
    sink = RerunSink(robot, RerunSettings(save=str(path), flush_s=0.05))

    def send(i: int) -> int:
        telemetry = decoder.decode(json.dumps(payload("arm-001", i)), topic_device="arm-001")
        sink.applied(AppliedSample("arm-001", time.time(), i * 0.1, telemetry, dict(telemetry.angles_rad)))
        return telemetry.timestamp_ms

    def change(previous: DeviceStatus, status: DeviceStatus, at: float) -> None:
        sink.status(StatusChange("arm-001", previous, status, at_mono_s=at, at_wall_s=at))

    for i in range(5):
        send(i)
    change(DeviceStatus.ONLINE, DeviceStatus.STALE, 1.0)
    lone_ms = send(12)
    change(DeviceStatus.STALE, DeviceStatus.OFFLINE, 11.0)
    sink.close()
    temporal, _ = read_rrd(path)
    cells = zip(times_ms(temporal), column(temporal, "/arms/arm-001/events", "TextLog:text"), strict=True)
    lines = [line for _, cell in cells if cell for line in cell if line.startswith("arm ")]
    assert lines == [
        "arm STALE (was ONLINE): its pose is the last one it sent",
        "arm OFFLINE (was STALE): its pose is the last one it sent",
    ]
    labels = rows_of(temporal, "/arms/arm-001/status", "Points3D:labels")
    assert list(labels.values()) == [["STALE"], ["OFFLINE"]]
    assert min(labels) < lone_ms < max(labels)


def test_a_late_sample_clears_the_label_after_it_not_behind_it(robot: RobotModel, tmp_path: Path) -> None:
    """A review: samples delivered late (a backlog after an outage), newer than the arm's last one but
    measured before the label's time, cleared it at their own time, behind the label: a viewer at the live end
    still saw STALE over the live arm."""
    path = tmp_path / "late.rrd"
    walk = _Walk(robot, path)
    walk.run(1.0, sending=True)
    walk.run(walk.config.health.stale_after_s + 0.5, sending=False)
    assert walk.mirror.statuses()["arm-001"] is DeviceStatus.STALE
    quiet = round((walk.config.health.stale_after_s + 0.5) * 10)
    walk.run(1.0, sending=True, lag=quiet - 1)  # the next after the last one sent on, delivered late
    assert walk.mirror.statuses()["arm-001"] is DeviceStatus.ONLINE
    walk.mirror.stop()
    temporal, _ = read_rrd(path)
    labels = rows_of(temporal, "/arms/arm-001/status", "Points3D:labels")
    [(stale_ms, stale)] = [(t, v) for t, v in labels.items() if v]
    assert stale == ["STALE"] and walk.sent[10] < stale_ms
    cleared = [t for t, v in labels.items() if not v]
    assert cleared and min(cleared) > stale_ms, labels


def test_status_text_names_each_error_bit() -> None:
    assert status_text({"shoulder_pan": 0, "gripper": 0}) == ""
    assert status_text({"elbow_flex": 0b100100}) == "elbow_flex: temperature, overload error"
    assert status_text({"shoulder_pan": 1, "wrist_flex": 2}) == (
        "shoulder_pan: voltage error; wrist_flex: angle sensor error"
    )


def test_the_rate_cap_skips_and_counts(robot: RobotModel, tmp_path: Path) -> None:
    path = tmp_path / "capped.rrd"
    # 10 Hz arrivals (2.3 s of receive time) against a 4 Hz cap with a burst of 2 (half a second's worth):
    # the bucket starts full and refills at 4 a second, so at most 2 + 4 x 2.3 = 11.2 samples per device get
    # through, and at least one fewer (the last refill may fall short of a whole token).
    settings = RerunSettings(save=str(path), max_rate_hz=4.0, burst_s=0.5, flush_s=0.05)
    sink = RerunSink(robot, settings)
    feed(sink)
    sink.close()
    stats = sink.stats()
    assert stats.delivered + stats.skipped == SAMPLES * len(DEVICES)
    assert 10 * len(DEVICES) <= stats.delivered <= 11 * len(DEVICES)
    table, _ = read_rrd(path)
    kept = sorted(rows_of(table, "/arms/arm-001/wrist", "Transform3D:translation"))
    assert len(kept) * len(DEVICES) == stats.delivered
    # The burst lets the first two through together; after it no two kept samples are 100 ms apart.
    assert kept[:2] == [T0_MS, T0_MS + 100]
    assert all(b - a >= 200 for a, b in itertools.pairwise(kept[1:]))


def test_jitter_under_the_cap_costs_nothing(robot: RobotModel, tmp_path: Path) -> None:
    # 10 Hz on average, arriving in pairs 20 ms apart (a stalled network releasing two at once): all kept
    # under the default 20 Hz cap.
    sink = RerunSink(robot, RerunSettings(save=str(tmp_path / "jitter.rrd")))
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    mono = time.monotonic()
    for i in range(40):
        telemetry = decoder.decode(json.dumps(payload("arm-001", i)), topic_device="arm-001")
        arrival = mono + (i // 2) * 0.2 + (i % 2) * 0.02
        sink.applied(AppliedSample("arm-001", time.time(), arrival, telemetry, dict(telemetry.angles_rad)))
    sink.close()
    assert (sink.stats().delivered, sink.stats().skipped) == (40, 0)


def test_a_host_stall_costs_a_normal_arm_nothing_and_a_flood_is_still_capped(
    robot: RobotModel, tmp_path: Path
) -> None:
    # The CI failure: the agent's MQTT thread stalls for 3 s, then a 10 Hz arm's backlog (30 messages)
    # arrives within a few milliseconds. Meanwhile another edge floods at 200 Hz. Default settings.
    settings = RerunSettings(save=str(tmp_path / "stall.rrd"))
    sink = RerunSink(robot, settings)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    mono = time.monotonic()
    arrivals: list[tuple[float, str, int]] = []
    for i in range(20):  # 2 s of normal traffic, then nothing for 3 s
        arrivals.append((mono + 0.1 * i, "arm-001", i))
    for k in range(30):  # the stall's backlog, 0.1 ms apart
        arrivals.append((mono + 1.9 + 3.0 + 0.0001 * k, "arm-001", 20 + k))
    for i in range(40):  # and on at 10 Hz
        arrivals.append((mono + 5.0 + 0.1 * i, "arm-001", 50 + i))
    flood_s = 9.0
    for i in range(int(200 * flood_s)):
        arrivals.append((mono + i / 200, "arm-002", i))
    for t, device, i in sorted(arrivals):
        telemetry = decoder.decode(json.dumps(payload(device, i)), topic_device=device)
        sink.applied(AppliedSample(device, time.time(), t, telemetry, dict(telemetry.angles_rad)))
    sink.close()
    table, _ = read_rrd(tmp_path / "stall.rrd")
    normal = rows_of(table, "/arms/arm-001/wrist", "Transform3D:translation")
    assert len(normal) == 90, "the stalled 10 Hz arm lost samples to the rate cap"
    flood = len(rows_of(table, "/arms/arm-002/wrist", "Transform3D:translation"))
    # The flood gets its burst (5 s x 20 Hz) and then the cap over its 9 s: about 280 of its 1800.
    burst = settings.max_rate_hz * settings.burst_s
    cap = burst + settings.max_rate_hz * flood_s
    assert cap - 2 <= flood <= cap + 1
    assert sink.stats().skipped == int(200 * flood_s) - flood


def test_samples_reach_the_sink_thread_when_the_fleet_goes_quiet(robot: RobotModel, tmp_path: Path) -> None:
    # Samples are handed to the sink's thread in groups; what a fleet leaves behind when it stops sending
    # is taken by the thread when its queue idles (flush_s / 2), not held until the next message or close.
    # flush_s 0.5: the three samples below are handed over within that of each other even on a busy machine,
    # so they make one batch.
    sink = RerunSink(robot, RerunSettings(save=str(tmp_path / "quiet.rrd"), flush_s=0.5))
    decoder = TelemetryDecoder(DecoderConfig(units=Units.DEGREES))
    for i in range(3):
        telemetry = decoder.decode(json.dumps(payload("arm-001", i)), topic_device="arm-001")
        sink.applied(
            AppliedSample("arm-001", time.time(), time.monotonic(), telemetry, dict(telemetry.angles_rad))
        )
    assert sink.stats().pending + sink.stats().delivered == 3
    wait_for(lambda: sink.worker.batches_sent and sink.stats().delivered == 3, 30, "the quiet fleet's batch")
    stats = sink.stats()
    assert (stats.delivered, stats.pending, sink.worker.batches_sent) == (3, 0, 1)
    sink.close()


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (RerunSettings(save="twin.txt"), "must name a .rrd file"),
        (RerunSettings(memory_limit="lots"), "is not a size"),
        (RerunSettings(max_rate_hz=0.0), "max_rate_hz"),
        (RerunSettings(burst_s=0.0), r"rerun.burst_s = 0.0 must be .* greater than 0.*burst_s = 5.0"),
        (RerunSettings(burst_s=math.inf), "rerun.burst_s = inf"),
        (RerunSettings(grpc_port=70000), "outside 0..65535"),
        (RerunSettings(serve=True, grpc_port=9000, web_port=9000), "different ports"),
        (RerunSettings(mesh_faces_per_arm=10), "at least 100"),
        (RerunSettings(mesh_faces_far=10), r"rerun.mesh_faces_far = 10 .* at least 100"),
        (RerunSettings(mesh_detailed_arms=-1), "mesh_detailed_arms = -1 must be 0 or more"),
    ],
)
def test_bad_settings_name_the_key_and_the_fix(settings: RerunSettings, message: str) -> None:
    with pytest.raises(RerunSettingsError, match=message):
        settings.validate()
