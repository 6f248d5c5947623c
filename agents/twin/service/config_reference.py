"""The agent config's reference, generated from the loader: docs/configuration.md and examples/agent.toml.

The sections, keys, types and defaults come from the config's own dataclasses (twin.service.config
`_SECTIONS`), so they cannot drift from what `twin run` accepts; what each key means is written once, here
(`KEY_DOCS`, `SECTION_DOCS`). `twin config reference` and `twin config example` print the two files;
tests/test_config_reference.py fails when a key has no meaning here or either file differs from what they
print (`make config-docs` writes both).
"""

from __future__ import annotations

import dataclasses
import enum
import json
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from twin.service.config import _SECTIONS

__all__ = ["KEY_DOCS", "SECTION_DOCS", "Key", "keys", "render_example", "render_reference"]

SECTION_DOCS: dict[str, str] = {
    "broker": "Where and how the agent connects (`twin.transport.broker.BrokerConfig`; the same settings "
    "and checks serve `twin edge-sim` and the benchmarks).",
    "telemetry": "What the agent subscribes to and how it reads a message (docs/telemetry.md).",
    "twin": "The twin itself: kinematic or physics, its model, USD recording, worker processes.",
    "health": 'When an arm counts as ONLINE, STALE or OFFLINE (docs/agent.md, "Health").',
    "http": "The HTTP API and the operator console (docs/http-api.md; docs/console.md).",
    "history": "Telemetry history in Delta Lake: every applied and rejected message, written in batches "
    "(docs/history.md).",
    "log": "The agent's JSON log lines.",
    "alarms": "The servo alarm thresholds (`twin.core.alarms.AlarmThresholds`): per alarm a raise level, a "
    "clear level below it and two durations. Their sources and what to do when one fires: "
    "docs/servo-health.md. A clear level at or above its raise level stops the agent at start-up.",
    "cloudwatch": 'CloudWatch metrics as Embedded Metric Format lines (docs/servo-health.md, "Cloud '
    'monitoring"); off while `emf_file` is empty.',
    "alerts": "Servo alarm transitions sent to an SNS topic, batched and rate-limited (docs/servo-health.md, "
    "\"Alarm e-mails\"); off while `topic_arn` is empty. The twin host's config names the stack's alarm "
    "topic.",
    "ros2": "The ROS 2 bridge: every arm as a `sensor_msgs/JointState` (docs/ros2.md; needs the `ros2` "
    "extra). Off by default.",
    "rerun": "The Rerun sink: the fleet as a `.rrd` recording and/or served to Rerun's web viewer on "
    "127.0.0.1 (docs/web.md). Off unless `save` or `serve` is set.",
}

KEY_DOCS: dict[str, str] = {
    "broker.url": (
        '`"iot"` = AWS IoT Core over WebSocket with SigV4. `"mqtt://host:port"` = plain MQTT 5. '
        '`"mqtts://host:port"` = MQTT 5 over TLS. Flag `--broker`.'
    ),
    "broker.region": "iot only. Empty = `AWS_REGION`, else `AWS_DEFAULT_REGION` or the AWS config's region.",
    "broker.endpoint": "iot only. Empty = looked up with `iot:DescribeEndpoint` (`iot:Data-ATS`).",
    "broker.client_id_prefix": (
        "The client id is this prefix plus 12 random hex digits, and the fleet's shared-subscription "
        "group is this prefix without its trailing `-`. Empty = this machine's own, `so101-twin-<host"
        " name>-` (the twin host's config sets `so101-twin-<stack name>-`), so two agents never split"
        " a fleet or evict each other. The IAM policy allows only this prefix. 1 to 100 letters, "
        "digits and `_ . : -`."
    ),
    "broker.ca_file": (
        "mqtts only. A PEM CA bundle, e.g. for a corporate TLS proxy. Empty = the system trust store."
    ),
    "broker.min_reconnect_delay_ms": (
        "Reconnect backoff floor. awscrt doubles the delay after each failed attempt, with full jitter."
    ),
    "broker.max_reconnect_delay_ms": (
        "Reconnect backoff cap: once the broker is back, the next attempt comes at most this long "
        "after. At the cap the mean wait is 1 s, IoT Core's connect limit per client id."
    ),
    "broker.keep_alive_s": (
        "MQTT keep-alive (5..1200). A silently dropped connection is noticed within about 1.5 keep-alives."
    ),
    "broker.per_connection_limit": (
        "Publishes per second one connection may carry; 0 = the broker's own (100 on `iot`, unlimited"
        " elsewhere). The connection pool plans to use 80 % of it (docs/scaling.md, \"IoT Core's "
        'per-connection quota"). Flag `--per-connection-limit`.'
    ),
    "broker.max_connections": (
        "The most connections a whole-fleet subscription grows to (1..64); listed devices are planned "
        "without it. On the twin host the stack's maxConnections sets it, and for the whole fleet its IAM "
        "policy allows that many pool client ids."
    ),
    "telemetry.topic_prefix": (
        "Topics are `{topic_prefix}/{device_id}/telemetry`. Plain topic levels (letters, digits, `.`,"
        " `_`, `-`) joined by `/`, without wildcards or a leading or trailing `/`. Flag "
        "`--topic-prefix`."
    ),
    "telemetry.devices": (
        'The devices to mirror: only their topics are subscribed. `["*"]` (the default) = every '
        "device under the prefix (`dt/lerobot/+/telemetry`, or the shared subscription under a "
        "budget), one twin each. Each id is listed once; any id an edge may publish as is taken (1 to "
        "128 printable characters without `/`, `+`, `#` or surrounding spaces, not `.` or `..`), but "
        "only one of 1 to 64 letters, digits, `-`, `_` or `.`, not `.` first nor `.json` last (the "
        "stack's rule and the calibration stores', `<id>.json`) can have a calibration of its own: "
        "`twin run` and `twin config check` note any other, and any two ids differing only in case "
        "(ids are case-sensitive, but a case-insensitive file system keeps their calibrations in one "
        "file). Flag `--devices`."
    ),
    "telemetry.units": (
        "What `position` means: `ticks` (raw servo), `degrees` or `range100` (LeRobot-normalised), or"
        " `auto`. With `auto`, each device's units are decided from evidence over the first messages,"
        " never guessed per message; until then its messages are rejected, as `units_undecided` unless"
        " they break another rule (a position no units allow is `out_of_range`). Set the units when you"
        " know them. Flag `--units`."
    ),
    "telemetry.calibration": (
        "One LeRobot calibration JSON for every arm that has none of its own (docs/agent.md, "
        '"Calibration"). Empty = the nominal SO-101.'
    ),
    "telemetry.calibrations": (
        "Where each arm's own calibration is kept, as `<device>.json`: a directory or "
        "`s3://bucket/prefix` (the twin host: the stack's `CalibrationUri`). Watched; empty = none. "
        "Fill a directory with `twin calibration push ARM FILE --store DIR` (without `--store`, push "
        "writes to the stack's store)."
    ),
    "telemetry.calibration_poll_s": (
        "How often the store of `calibrations` is listed (1..3600). A new or changed file takes "
        "effect within this long."
    ),
    "telemetry.max_payload_bytes": (
        "Larger messages are rejected as `too_large` (IoT Core caps messages at 128 KiB = 131072 "
        "bytes). At most 1048576."
    ),
    "telemetry.max_devices": (
        "The most twins a fleet subscription may create, across all workers. A device counts once it "
        "has sent a valid message, so messages that never decode (not JSON, an invented topic) take "
        "no place. Valid messages from further devices are counted as `too_many_devices` (untracked) "
        "and logged at most every 10 s. The default is a whole fleet for one host: 2,000 arms at 10 "
        "Hz are 20,000 publishes a second, the account's default IoT Core inbound quota. At most "
        "10000. A `devices` list longer than this is refused."
    ),
    "telemetry.forget_offline_after_s": (
        "Forget an arm silent this long (seconds; OFFLINE from `health.offline_after_s` of silence on) as "
        'an operator would (docs/console.md, "Forget an arm"), unless an alarm of it waits for a person '
        "(ACTIVE or LATCHED), it is listed in `devices`, or its messages still arrive, all refused (the "
        "sweep tries it again every 5 s): "
        "for a fleet whose ids come and go, so retired arms give their `max_devices` places to new ones. "
        "One event says so. 0, the default, never; else longer than `health.offline_after_s`, e.g. 604800 "
        "for a week."
    ),
    "telemetry.forget_unseen_after_s": (
        "Forget an arm silent this long (seconds) even when an alarm of it waits for a person (ACTIVE or "
        "LATCHED), which `forget_offline_after_s` keeps: a WARNING event names each such alarm. Without it a "
        "fleet whose arms leave with an alarm up fills every `max_devices` place with them, and new arms are "
        "refused until a person acknowledges or forgets them. 0, the default, never; else at least "
        "`forget_offline_after_s`, which must be set, e.g. 2592000 for 30 days."
    ),
    "twin.mode": (
        "`kinematic`: the twin shows exactly the measured pose. `physics`: the measured pose is the "
        "target of the simulated servos, and the worker steps the simulation. Flag `--mode`."
    ),
    "twin.model": "MJCF file. Empty = the bundled SO-101.",
    "twin.record_dir": (
        "Record a USD session here (`session-<UTC time>-<pid>.<record_format>`, and `-<n>` before the"
        " format for the n-th file after a rotation). A session that recorded no sample (a worker given"
        " no arm) is removed when it closes. Empty = no recording. Flag `--record-dir`."
    ),
    "twin.record_format": (
        "`usdc` (binary: each flush appends, constant cost, for long runs) or `usda` (text: readable,"
        " but every flush rewrites the whole file)."
    ),
    "twin.physics_rate_hz": "physics mode: how often the worker steps the simulation.",
    "twin.record_flush_s": "Seconds between saves of the USD recording. The final save happens on stop.",
    "twin.workers": (
        'Processes that mirror the fleet, each a share of the devices (docs/scaling.md, "Workers"). '
        "`0`: one per core for the whole fleet, one per 1,000 expected msg/s for a listed one, one "
        "while `[rerun]` is on; `1`: one process. At most 64. Flag `--workers`."
    ),
    "twin.record_max_mb": (
        "The USD recording rotates to a new session file at the first save that takes its file to this "
        "size or past it, so a file ends a save's worth above it (a stage "
        'also lives in memory while it records: rotation bounds that too). docs/agent.md, "Bounds and '
        'restarts".'
    ),
    "twin.record_max_age_s": "... or once the session file is this old.",
    "twin.record_budget_mb": (
        "The session files in `record_dir` are kept within this, the live one counted at "
        "`record_max_mb`: at each rotation the oldest are deleted. At least `record_max_mb`."
    ),
    "twin.record_rate_hz": (
        "Each arm is recorded at most this many samples a second; the rest are counted as `skipped`. "
        "A USD sample costs the recording's one thread about 30 `json.loads` of an edge message (0.3 ms "
        "where `json.loads` takes 10 µs; `twin bench usd`), so a large fleet at 10 Hz is more than it can "
        "keep up with."
    ),
    "twin.state_file": (
        "Where the servo alarms an agent restart must not forget (ACTIVE, ACKNOWLEDGED, LATCHED) are "
        "kept, written atomically. Empty = not kept: a restart starts with every alarm NORMAL and "
        "forgets each acknowledgement, so set it for an agent of your own beside real arms "
        "(`\"out/state.json\"`). The twin host's config names a file in the service's state "
        "directory (`/var/lib/so101-twin-agent/state.json`)."
    ),
    "twin.events_file": (
        "Where the agent appends its events (the console's Events page), to read them back at its next "
        "start: without it a restart begins the page anew, and the Sessions page no longer knows the "
        "alarms raised in a session from before it. The alarm events go to this file, the status, "
        "rejected and twin events to `<stem>.bulk<suffix>` beside it, the calibration, agent, worker and "
        "broker events to `<stem>.lifecycle<suffix>`, so a flood of one kind never rotates the others "
        "out. Each file is renamed `<name>.1` (the older) once past `events_capacity` x 1,000 bytes (x 500 "
        "for the bulk pair), so each pair holds all the store keeps of its kinds, and the six files take "
        "at most `events_capacity` x 5,000 bytes (100 MB at the default 20,000). Empty = memory only. "
        "The twin host's config names `/var/lib/so101-twin-agent/events.jsonl`."
    ),
    "twin.events_capacity": (
        "How many events the agent keeps in memory for the Events page, its exports and the Sessions "
        "page's alarm counts, and each worker process until the agent collects them; about 300 bytes "
        "an event. 100..100000. Alarm, calibration, agent, worker and broker events keep half of it for "
        "themselves: a flood of status, rejected and twin events (a loaded host's arms going STALE and "
        "ONLINE) takes the rest and the room they leave, never their half. Within that half, "
        "calibration, agent, worker and broker events keep a twentieth (1,000 of 20,000) that a flood "
        "of alarms cannot take. With `events_file` set, a restart reads back the newest of each of "
        "those three parts the files hold, within it, and the files' size grows with it (`events_file`)."
    ),
    "twin.shutdown_budget_s": (
        "How long a stop may take in all: the workers handle what is queued and flush their sinks "
        "(history's last commit) within it, what could not be written is logged, and a worker still "
        "running then is killed. 10..600. systemd's `TimeoutStopSec` must be longer: the host's unit "
        "has 90 s, so a budget above 60 s in `agent.local.toml` is cut short by systemd."
    ),
    "health.expected_rate_hz": "The edge's publish rate.",
    "health.stale_periods": (
        "STALE after this many expected periods with no valid message (3 at 10 Hz = 0.3 s)."
    ),
    "health.offline_after_s": (
        "OFFLINE after this many seconds with no valid message. Must be longer than the stale time."
    ),
    "health.window_s": "Sliding window for the message rate and the latency percentiles.",
    "http.listen": (
        "HTTP address. Loopback only by default, because the API has no authentication. Port 0 picks "
        "a free port. Flag `--http`."
    ),
    "http.stream_rate_hz": "The most events per second on `/stream`.",
    "http.allowed_hosts": (
        "Host names (or addresses, no port) the server answers to besides the loopback ones "
        "(`localhost`, `127.0.0.1`, `[::1]`, ...). Any other `Host` gets 400: a page that reaches the"
        " port under its own name (DNS rebinding) cannot read the API. A server listening on one "
        "specific non-loopback address answers to that address too."
    ),
    "http.max_connections": "Connections served at once; more get 503.",
    "http.timeout_s": (
        "A request head or body that stalls, or a client that stops reading what it is sent, is cut "
        "off after this long."
    ),
    "http.max_body_bytes": "The largest request body (1024 .. 1 MiB); a larger one gets 413.",
    "http.console_rate_hz": "How often the operator console's pages are updated (at most `stream_rate_hz`).",
    "http.session_gap_s": "A gap this long ends a session on the console's Sessions page (docs/console.md).",
    "http.session_files_mb": (
        "The Sessions page's files kept on disk to serve again, at most this many MB; beyond, the ones "
        "used longest ago are removed (and made again if asked for)."
    ),
    "history.uri": (
        'A directory (`"out/history"`) or `"s3://<bucket>/history"`. Empty = no history. Flag `--history`.'
    ),
    "history.region": "S3 region; empty = `AWS_REGION` or the instance's region.",
    "history.commit_every_s": "A commit at least this often while rows wait.",
    "history.commit_every_rows": "... or as soon as this many rows wait.",
    "history.max_buffer_rows": (
        "Rows held in memory while commits fail; beyond, the oldest are dropped and counted."
    ),
    "history.queue_max": (
        "Each mirror's queue of rows in front of the history writer process, which fills only while the "
        "writer is out of reach or behind (a saturated host); beyond, the oldest are dropped and counted."
    ),
    "history.maintain_every_s": (
        "Compaction, checkpoint and vacuum interval; 0 = never (another writer maintains)."
    ),
    "history.vacuum_retention_hours": (
        "Files replaced by compaction are deleted after this long, in whole hours rounded up (a reader "
        "still on an older version needs them); 0 = at once."
    ),
    "history.keep_days": (
        "Whole UTC days kept besides today; the newest keep_days + 1 days holding rows are kept whatever the "
        "clock says (docs/history.md). 0 = keep all."
    ),
    "history.writer_nice": (
        "How much nicer than the mirrors the history writer process runs, 0 to 19: its commits' bursts of "
        "Parquet encoding then yield to the mirrors (docs/history.md). 0 on a host with cores to spare."
    ),
    "log.level": "`DEBUG`, `INFO`, `WARNING` or `ERROR`. Flag `--log-level`.",
    "alarms.enabled": "Evaluate the servo alarms at all (docs/servo-health.md).",
    "alarms.latch": (
        "An alarm whose condition went away unacknowledged stays LATCHED until acknowledged, so a "
        "servo that overheated at night is still on the board in the morning. `false`: it goes back "
        "to NORMAL by itself."
    ),
    "alarms.servo_version": (
        'The arm\'s STS3215 version, `"7.4v"` (the follower\'s bill of materials) or `"12v"`: its stall'
        " torque converts the model's holding torque into the load the servo should report (model "
        "mismatch)."
    ),
    "alarms.temperature_warning_c": (
        "Over-temperature (warning) is raised at or above this many degrees C: the top of the servo's"
        " operating range."
    ),
    "alarms.temperature_warning_clear_c": "... and cleared at or below this (must be lower: hysteresis).",
    "alarms.temperature_critical_c": (
        "Over-temperature critical is raised at or above this: 5 C before the servo's own 70 C cut-out."
    ),
    "alarms.temperature_critical_clear_c": "... and cleared at or below this.",
    "alarms.temperature_raise_after_s": (
        "Seconds a temperature must stay at or above a raise level before the alarm is raised "
        "(filters a one-sample glitch)."
    ),
    "alarms.temperature_clear_after_s": (
        "Seconds it must stay at or below the clear level before the alarm clears (a servo hovering "
        "at the line does not flap)."
    ),
    "alarms.current_a": (
        "Over-current (critical) is raised at or above this many amperes: 80 % of the servo's 3.25 A "
        "protection current."
    ),
    "alarms.current_clear_a": "... and cleared at or below this (65 %).",
    "alarms.gripper_current_a": (
        "The gripper's over-current level (80 % of the 1.625 A LeRobot sets on the jaw)."
    ),
    "alarms.gripper_current_clear_a": "... and its clear level (65 %).",
    "alarms.current_raise_after_s": (
        "Seconds a current must stay at or above its level: half the servo's 2 s trip time, so the "
        "alarm comes before the cut-out."
    ),
    "alarms.current_clear_after_s": "Seconds at or below the clear level before an over-current clears.",
    "alarms.overload_percent": (
        "Sustained overload (warning) is raised at or above this |load|, % of stall torque: the "
        "servo's own overload line."
    ),
    "alarms.overload_clear_percent": "... and cleared at or below this.",
    "alarms.gripper_overload_percent": "The gripper's overload level (LeRobot writes 25 % to the jaw).",
    "alarms.gripper_overload_clear_percent": "... and its clear level.",
    "alarms.overload_raise_after_s": (
        "Seconds at or above the overload level: half the servo's 2 s overload countdown."
    ),
    "alarms.overload_clear_after_s": "Seconds at or below the clear level before an overload clears.",
    "alarms.mismatch_percent": (
        "Model mismatch (warning) is raised when |measured load| and the load the model says holding "
        "the pose takes differ by this many percentage points, while the joint is still: contact, a "
        "payload or a failing servo."
    ),
    "alarms.mismatch_clear_percent": "... and cleared at or below this difference.",
    "alarms.mismatch_raise_after_s": (
        "Seconds the difference must last (joint still) before the alarm is raised."
    ),
    "alarms.mismatch_clear_after_s": "Seconds at or below the clear difference before it clears.",
    "alarms.still_velocity_rad_s": (
        "A joint counts as still when its reported speed and the pose's own rate of change are both "
        "at most this (rad/s) and its Moving flag is not set; only then is it checked against the "
        "model."
    ),
    "alarms.mismatch_joints": (
        "The joints checked against the model (the jaw grasps by design, so it is left out)."
    ),
    "alarms.servo_error_bits": (
        "The servo's own error bits (its status register, from edges that send `status`) that raise "
        "`servo_error`: any of voltage, sensor, temperature, current, angle and overload."
    ),
    "alarms.servo_error_raise_after_s": (
        "How long an error bit must be set before `servo_error` is raised (0: the first reading; the servo "
        "sets the bit only once its own protection acted)."
    ),
    "alarms.servo_error_clear_after_s": (
        "How long the status must show none of those bits before `servo_error` clears."
    ),
    "cloudwatch.emf_file": (
        "Where to append CloudWatch Embedded Metric Format lines (the instance: "
        "`/var/log/so101-twin/emf.log`, which the CloudWatch agent ships). Empty: no CloudWatch "
        "metrics."
    ),
    "cloudwatch.agent_name": (
        "The metrics' `Agent` dimension; the stack renders its stack name, which its alarms watch."
    ),
    "cloudwatch.interval_s": (
        "Seconds between EMF writes (one line for the fleet, one per alarm severity). It must divide 60 "
        "(60, 30, 20, 15, 10, 5, ...): the stack's alarms judge each minute, so every minute needs whole "
        "intervals, the same number of them."
    ),
    "alerts.topic_arn": (
        "The SNS topic; empty: nothing is sent. The caller needs `sns:Publish` on it (and, for an "
        "encrypted topic, `kms:GenerateDataKey` and `kms:Decrypt` on its key)."
    ),
    "alerts.region": "The topic's region; empty = `[broker] region`, else the AWS config's.",
    "alerts.warnings": "Send warnings too; critical alarms are always sent.",
    "alerts.flush_s": "How often what came in is sent, as one message (0..9.5: within 10 s of the change).",
    "alerts.max_per_hour": (
        "Messages an hour once `burst` is used up; changes beyond wait for the next message allowed."
    ),
    "alerts.burst": "Messages that may go out at once.",
    "ros2.enabled": "Publish the arms on ROS 2. Flag `--ros2`.",
    "ros2.topic": (
        "The ROS topic per arm. `{arm}` is the device id as a ROS name (docs/ros2.md). A fixed topic "
        'such as `"/joint_states"` suits a single arm only: the agent refuses it with several '
        'configured devices, and with `devices = ["*"]` the first arm seen gets the topic and every '
        "other arm is refused."
    ),
    "ros2.joint_names": (
        "The joint names in the message: a preset (`so101`, `so_arm101_usd`; docs/ros2.md) or six "
        "names for `shoulder_pan, shoulder_lift, elbow_flex, wrist_flex, wrist_roll, gripper`, in "
        "that order."
    ),
    "ros2.domain_id": (
        "The ROS 2 domain. `-1` = the `ROS_DOMAIN_ID` environment variable, else 0, as every ROS 2 node does."
    ),
    "ros2.frame_id": "`header.frame_id` of every message.",
    "ros2.velocity": (
        "Fill `velocity` (rad/s) when every joint of the sample reports a servo speed. Turn it off "
        "for Isaac Sim (docs/ros2.md)."
    ),
    "ros2.interface": (
        'The network interface DDS uses, by name (`"ens5"`) or address. Empty = Cyclone picks one.'
    ),
    "ros2.peers": (
        "Unicast discovery peers (IPv4 addresses or host names), for networks without multicast such as EC2; "
        "the agent refuses one that does not resolve to IPv4."
    ),
    "ros2.max_pending": (
        "Samples queued for the DDS thread before the oldest are dropped (counted): about a second of"
        " 100 arms at 10 Hz."
    ),
    "rerun.save": '`.rrd` file to write (its folder is created); "" writes none.',
    "rerun.serve": "Serve the stream (gRPC) and the web viewer (HTTP), both on 127.0.0.1.",
    "rerun.grpc_port": "The stream's port (Rerun's default); 0 picks a free one.",
    "rerun.web_port": "The web viewer's port; 0 picks a free one.",
    "rerun.memory_limit": (
        "What the stream keeps for viewers that connect later; the oldest data is dropped first, the "
        'static meshes never (Rerun sizes: `"2GiB"`, or a share of RAM: `"10%"`).'
    ),
    "rerun.max_rate_hz": (
        "Per device, at most this many samples a second enter the stream; the rest are counted as `skipped`."
    ),
    "rerun.burst_s": (
        "... after a burst of this many seconds' worth of `max_rate_hz` (100 samples by default): "
        "when the host stalls the agent for a few seconds and a device's backlog then arrives at "
        "once, an arm under the cap loses nothing (a 10 Hz arm's stall of up to 10 s passes whole); a"
        " flooding edge gets the burst once, then the cap."
    ),
    "rerun.max_fleet_rate_hz": (
        "... and at most this many a second for the whole fleet: past it each device gets an equal share "
        "(100 arms at 10 Hz pass whole, 200 get 5 Hz each), its burst scaled with it; a device silent for "
        "10 s no longer counts. The rest are "
        "counted as `skipped`. The sink's cost is per sample: a lower rate per arm keeps a large fleet's "
        "stream whole instead of dropping seconds of it (docs/web.md)."
    ),
    "rerun.flush_s": "Samples are sent per device in batches at most this often: the stream's delay.",
    "rerun.max_batches_per_s": (
        "And at most this many device batches a second in all: with 100 arms each waits 5 s."
    ),
    "rerun.mesh_faces_per_arm": "Triangles of a detailed arm in the fleet view (docs/web.md).",
    "rerun.mesh_detailed_arms": (
        "How many arms, in order of appearance, are detailed (the focus arm always is); 0: only the "
        "focus arm."
    ),
    "rerun.mesh_faces_far": "Triangles of every other arm (at least 100; never more than a detailed arm).",
    "rerun.fleet_spacing_m": "Distance between arms in the fleet grid.",
    "rerun.focus_device": 'The arm the plots open on ("" = the first arm seen).',
    "rerun.max_pending": "The sink's queue; beyond it the oldest samples are dropped (counted).",
    "rerun.save_max_mb": (
        "The saved `.rrd` rotates to a new file once it reaches this size (it grows about 1.5 MB a "
        "second at 200 arms), or twice the arms' meshes it starts with if that is more (a warning says "
        'so; docs/web.md, "`.rrd` files").'
    ),
    "rerun.save_max_age_s": "... or once it is this old.",
    "rerun.save_budget_mb": (
        "The rotated files beside the saved one are kept within this, the live one counted at the "
        "size it rotates at; the oldest are deleted first. At least `save_max_mb`."
    ),
}


@dataclass(frozen=True)
class Key:
    """One key of the config: its section, name, default (as TOML writes it), TOML type and meaning."""

    section: str
    name: str
    default: Any
    type: str
    meaning: str

    @property
    def dotted(self) -> str:
        return f"{self.section}.{self.name}"


def keys() -> Iterator[Key]:
    """Every key of every section, in the loader's order; KeyError for a key with no meaning in KEY_DOCS."""
    for section, cls in _SECTIONS.items():
        for f in dataclasses.fields(cls):
            # Typed as TOML holds it: a tuple default is a list there, not the "string" the reference said.
            default = _toml_default(_field_default(f))
            yield Key(section, f.name, default, _type_of(default), KEY_DOCS[f"{section}.{f.name}"])


def _field_default(f: dataclasses.Field[Any]) -> Any:
    # The declared default, not an instance's: BrokerConfig fills an empty client_id_prefix with this
    # machine's.
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    raise ValueError(f"config field {f.name} has no default")


def _toml_default(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, tuple):
        return list(value)
    return value


def _type_of(value: Any) -> str:
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, float):
        return "number"
    if isinstance(value, list):
        return "list of strings"
    return "string"


def toml_value(value: Any) -> str:
    """A default as TOML writes it (strings, booleans, numbers, lists of strings are all there is)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        # The shortest text that reads back as the same number (repr), with a point so TOML reads a float.
        text = repr(value)
        return text if any(c in text for c in ".en") else f"{text}.0"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return json.dumps(str(value))


REFERENCE_INTRO = (
    "Every key of the agent's TOML config (`twin run --config FILE`; `--config` may be given more than once, "
    "each file's keys winning over the ones before it), its type, its default and what it means. "
    "`examples/agent.toml` is the same list as a file with every default; `twin config check FILE` validates "
    "one. The agent checks everything at start-up: an unknown section or key is an error (`did you mean "
    "...?`), a bad value stops it with the key, the value and the fix (exit code 2). A key left out keeps "
    "its default. On the twin host, `/etc/so101-twin/agent.toml` is generated from the stack's settings and "
    '`/etc/so101-twin/agent.local.toml` is yours (docs/deploy.md, "What the instance runs").'
)
EXAMPLE_INTRO = (
    "The so101-twin agent config with every key at its default (generated from the loader by `twin config "
    "example`; docs/configuration.md is the same as a table). Copy the keys you change; a key left out keeps "
    "its default. Run with: twin run --config FILE"
)


def render_reference() -> str:
    """docs/configuration.md."""
    lines = [
        "# Agent configuration reference",
        "",
        "<!-- Generated from the config loader by `twin config reference` (`make config-docs`); edit the",
        "     meanings in agents/twin/service/config_reference.py, not here. -->",
        "",
        *textwrap.wrap(REFERENCE_INTRO, 110, break_on_hyphens=False),
    ]
    current = ""
    for key in keys():
        if key.section != current:
            current = key.section
            lines += [
                "",
                f"## `[{current}]`",
                "",
                *textwrap.wrap(SECTION_DOCS[current], 110, break_on_hyphens=False),
                "",
                "| key | type | default | meaning |",
                "|---|---|---|---|",
            ]
        lines.append(f"| `{key.name}` | {key.type} | `{toml_value(key.default)}` | {key.meaning} |")
    return "\n".join(lines) + "\n"


def render_example() -> str:
    """examples/agent.toml: every key at its default, each with its meaning as a comment."""
    lines = [f"# {line}" for line in textwrap.wrap(EXAMPLE_INTRO, 106, break_on_hyphens=False)]
    current = ""
    for key in keys():
        if key.section != current:
            current = key.section
            lines += [
                "",
                *(f"# {line}" for line in textwrap.wrap(SECTION_DOCS[current], 106, break_on_hyphens=False)),
                f"[{current}]",
            ]
        lines += [f"# {line}" for line in textwrap.wrap(key.meaning, 106, break_on_hyphens=False)]
        lines.append(f"{key.name} = {toml_value(key.default)}")
    return "\n".join(lines) + "\n"
