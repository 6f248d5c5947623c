"""Servo alarm transitions as notifications: batched, rate-limited messages to an SNS topic (e-mail and more).

The twin host publishes straight to the stack's alarm topic (its role may `sns:Publish` on that topic only),
so a person hears of a servo alarm within seconds, with what happened, instead of a CloudWatch alarm on a
once-a-minute metric that names neither the arm nor the servo. The agent hands every alarm transition
(raised, cleared, acknowledged, reset) it wants sent to `AlertPublisher.offer`; the publisher's thread sends
what came in once every `flush_s` (at most 9.5 s, so with the agent's half-second collection a transition is
sent within 10 s):

- one message per flush, however many transitions: each alarm once, with its latest state, how many times
  it changed since the last message, and its value, threshold and message (as many alarms as fit in SNS's
  256 KiB, the critical first: the rest wait for the next message);
- a token bucket bounds the messages: `burst` at once, then `max_per_hour`; transitions that arrive while it
  is empty wait and go out together in the next message it allows, so a flapping servo cannot flood anyone's
  mailbox, and nothing is dropped (beyond `max_pending` alarms, the oldest warnings, then the oldest
  critical ones, are summed up as a count);
- a publish that fails (no network, throttled) keeps the batch for the next flush; the stop's last flush
  sends what is pending beyond the limit (a restart never sends it), and logs what it could not send.

Pure but for the thread and the injected `publish(subject, body)` (boto3's SNS client in the agent, a list in
tests); the clock is injected too.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from twin.core.alarms import AlarmKind, what_to_do
from twin.core.aws import region_or_env
from twin.output.sinks import SinkStats
from twin.robot import so101, sts3215

log = logging.getLogger(__name__)

# A transition is published on the flush after it arrives; the agent collects its mirrors' events every
# 0.5 s, so a flush interval of at most this keeps the whole path within 10 s.
MAX_FLUSH_S = 9.5
# SNS refuses a subject over 100 characters (ASCII, no line breaks).
SUBJECT_MAX = 100
# ... and a message over 256 KiB of UTF-8: a fleet's burst of alarms (500 still servos mismatching at once)
# as one message was refused at every flush, so no e-mail went out again.
BODY_MAX = 262_144
# A message names an alarm's last this many changes and counts the rest: a servo flapping through an hour's
# outage of SNS would otherwise make one line of thousands of words, and hold them all in memory.
ACTIONS_KEPT = 10
# The stop sends what is pending in this many messages at most (a burst too big for one takes a few).
STOP_MESSAGES_MAX = 20
# The longest alarm message an e-mail quotes whole (the agent's own are about 200 characters).
MESSAGE_TEXT_MAX = 2000

Publish = Callable[[str, str], None]


@dataclass(frozen=True, slots=True)
class Alert:
    """One alarm transition, as the notification names it."""

    alarm_id: str
    device: str
    joint: str
    kind: str
    severity: str  # warning | critical
    action: str  # raised | cleared | acknowledged | reset
    state: str  # the alarm's state after it: ACTIVE, ACKNOWLEDGED, LATCHED, NORMAL
    value: float | None
    threshold: float | None
    unit: str
    message: str
    at: float  # wall-clock epoch seconds


@dataclass
class _Pending:
    latest: Alert
    first_at: float
    changes: int = 1
    actions: list[str] = field(default_factory=list)
    # The value of its last raise: a servo error that cleared since holds no bits, its advice needs them.
    raised_value: float | None = None


@dataclass(frozen=True, slots=True)
class AlertCounters:
    offered: int
    published_messages: int
    published_alerts: int
    failures: int
    delayed: int  # flushes the rate limit held back
    pending: int
    last_error: str


class AlertPublisher:
    """Batches alarm transitions and publishes them (module doc). `start()`/`stop()` run the flush thread;
    `flush()` does one round on the calling thread."""

    def __init__(
        self,
        publish: Publish,
        *,
        agent_name: str,
        how_to_acknowledge: str,
        flush_s: float = 5.0,
        max_per_hour: int = 30,
        burst: int = 10,
        max_pending: int = 500,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 0 < flush_s <= MAX_FLUSH_S:
            raise ValueError(
                f"flush_s = {flush_s} must be in (0, {MAX_FLUSH_S}] so an alarm is sent within 10 s"
            )
        if max_per_hour < 1 or burst < 1 or max_pending < 1:
            raise ValueError("max_per_hour, burst and max_pending must each be at least 1")
        self._publish = publish
        self.agent_name = agent_name
        self.how_to_acknowledge = how_to_acknowledge
        self.flush_s = flush_s
        self._rate = max_per_hour / 3600.0
        self._burst = float(burst)
        self._tokens = float(burst)
        self._max_pending = max_pending
        self._clock = clock
        self._refilled = clock()
        self._lock = threading.Lock()
        self._pending: OrderedDict[str, _Pending] = OrderedDict()
        self._overflow = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._offered = 0
        self._messages = 0
        self._alerts = 0
        self._failures = 0
        self._delayed = 0
        self._last_error = ""

    # -- in --------------------------------------------------------------------------------------------

    def offer(self, alert: Alert) -> None:
        """Queue a transition for the next flush; never blocks for long (any thread)."""
        with self._lock:
            self._offered += 1
            entry = self._pending.get(alert.alarm_id)
            if entry is None:
                if len(self._pending) >= self._max_pending and not self._make_room(alert):
                    self._overflow += 1
                    return
                entry = self._pending[alert.alarm_id] = _Pending(alert, alert.at, 1, [alert.action])
            else:
                entry.latest = alert
                entry.changes += 1
                entry.actions.append(alert.action)
                del entry.actions[:-ACTIONS_KEPT]
            if alert.action == "raised":
                entry.raised_value = _raised(entry.raised_value, alert)

    def _make_room(self, alert: Alert) -> bool:
        """With `max_pending` alarms waiting (under the lock): push out the oldest warning, counted, so that
        a fleet's burst of warnings never turns a critical alarm into a bare count (nor the subject into a
        warning's); with none, the oldest critical one for a critical `alert`. False: `alert` is the one
        counted (a warning, with every waiting alarm critical)."""
        victim = next((k for k, e in self._pending.items() if e.latest.severity != "critical"), None)
        if victim is None and alert.severity != "critical":
            return False
        if victim is None:
            self._pending.popitem(last=False)
        else:
            del self._pending[victim]
        self._overflow += 1
        return True

    # -- out -------------------------------------------------------------------------------------------

    def flush(self, *, last: bool = False) -> bool:
        """Publish what is pending as one message if the rate limit allows; True when a message went out.
        `last` (the stop's flush) sends it even when the limit is used up: a restart never sends it again."""
        with self._lock:
            if not self._pending and not self._overflow:
                return False
            now = self._clock()
            self._tokens = min(self._burst, self._tokens + (now - self._refilled) * self._rate)
            self._refilled = now
            if self._tokens < 1.0 and not last:
                self._delayed += 1
                return False
            # Copies: transitions that arrive while this one is published stay for the next message.
            originals = list(self._pending.values())
            batch = [
                _Pending(e.latest, e.first_at, e.changes, list(e.actions), e.raised_value) for e in originals
            ]
            overflow = self._overflow
        subject, body, listed = self.compose(batch, overflow)
        try:
            self._publish(subject, body)
        except Exception as exc:  # the next flush tries again with everything still pending
            with self._lock:
                self._failures += 1
                self._last_error = f"{type(exc).__name__}: {exc}"
            log.warning("alarm notification not published (kept for the next try): %s", exc)
            return False
        with self._lock:
            self._tokens = max(0.0, self._tokens - 1.0)
            self._messages += 1
            self._alerts += len(listed)
            self._last_error = ""
            ids = {id(entry) for entry in listed}
            for original, sent in zip(originals, batch, strict=True):
                if id(sent) not in ids:
                    continue  # no room in this message: it waits for the next
                current = self._pending.get(sent.latest.alarm_id)
                if current is not original:
                    continue  # gone (pushed out) or a new entry since
                if current.changes <= sent.changes:
                    del self._pending[sent.latest.alarm_id]
                else:
                    current.changes -= sent.changes
                    current.actions = current.actions[-current.changes :]
                    current.first_at = current.latest.at
            self._overflow -= overflow
        log.info(
            "alarm notification published",
            extra={"event": "alert_published", "alarms": len(listed), "subject": subject},
        )
        return True

    def compose(self, batch: Iterable[_Pending], overflow: int = 0) -> tuple[str, str, list[_Pending]]:
        """The message for a batch: a subject naming the worst alarm, a body with every alarm that fits in
        SNS's size (the critical first), and the entries listed; the others wait for the next message."""
        entries = sorted(batch, key=lambda e: (e.latest.severity != "critical", e.first_at))
        closing = ["How to acknowledge:", self.how_to_acknowledge]
        # The closing lines, and the lines saying what was left out (a few hundred bytes at most).
        room = BODY_MAX - _size(closing) - 512
        lines: list[str] = []
        listed: list[_Pending] = []
        for entry in entries:
            block = _describe(entry)
            if listed and _size(block) > room:
                break
            room -= _size(block)
            lines += block
            listed.append(entry)
        if len(listed) < len(entries):
            lines += [
                f"... and {len(entries) - len(listed)} more alarm(s) changed: too many for one message, "
                "they follow in the next.",
                "",
            ]
        if overflow:
            lines += [f"... and {overflow} more alarm(s) changed (too many to list; see the console).", ""]
        first = entries[0].latest if entries else None
        if first is not None:
            more = len(entries) - 1 + overflow
            subject = _fit_device(
                f"[{self.agent_name}] {first.severity.upper()} ",
                first.device,
                f" {first.joint} {first.kind} {first.action}" + (f" (+{more} more)" if more else ""),
            )
        else:
            subject = f"[{self.agent_name}] {overflow} servo alarm(s) changed"
        return _subject(subject), "\n".join(lines + closing), listed

    def counters(self) -> AlertCounters:
        with self._lock:
            return AlertCounters(
                offered=self._offered,
                published_messages=self._messages,
                published_alerts=self._alerts,
                failures=self._failures,
                delayed=self._delayed,
                pending=len(self._pending) + self._overflow,
                last_error=self._last_error,
            )

    def sink_stats(self) -> SinkStats:
        """The publisher as an output in /state `agent.sinks` and /metrics: a publish that keeps failing (the
        role, the topic's key) held every servo alarm e-mail back with only a log line to say so. What waits
        is kept while it retries (past max_pending, as a count in the next e-mail), so no `dropped`:
        `errors` and `last_error` tell it."""
        c = self.counters()
        return SinkStats(
            name="alerts",
            delivered=c.published_alerts,
            errors=c.failures,
            pending=c.pending,
            last_error=c.last_error,
        )

    # -- thread ----------------------------------------------------------------------------------------

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="twin-alerts", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.flush_s):
            try:
                self.flush()
            except Exception:
                log.exception("alarm notification flush failed")

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the thread, then send what is pending, the rate limit's used up or not (the events of this
        run are never sent again): up to STOP_MESSAGES_MAX messages, begun within `timeout` of the call, so
        a slow SNS cannot hold the agent's stop past its budget (one publish begun may still take boto's
        own timeouts). What is left is logged, since nothing else would say it was never sent."""
        deadline = self._clock() + timeout
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        try:
            for _ in range(STOP_MESSAGES_MAX):
                if self._clock() >= deadline or not self.flush(last=True):
                    break
        except Exception:
            log.exception("alarm notification flush failed")
        unsent = self.counters()
        if unsent.pending:
            log.warning(
                "%d alarm(s) changed but were not notified (%s): the console's Events page lists them",
                unsent.pending,
                unsent.last_error or "the agent stopped first",
                extra={"event": "alerts_unsent", "alarms": unsent.pending},
            )


def _describe(entry: _Pending) -> list[str]:
    """One alarm's lines in a message: what changed, its value, its message, what to do, its id and time."""
    a = entry.latest
    value = "no value" if a.value is None else f"{a.value:.3g} {a.unit}".strip()
    threshold = "" if a.threshold is None else f", threshold {a.threshold:.3g} {a.unit}".rstrip()
    if a.kind == "servo_error" and a.value is not None:
        # Its value is the status's error bits: named, and no threshold (any set bit raises).
        bits = int(a.value)
        names = ", ".join(sts3215.status_names(bits)) or "none"
        value, threshold = f"status bits {bits} ({names})", ""
    last = "" if entry.changes == len(entry.actions) else f", the last {len(entry.actions)}"
    history = (
        f" ({entry.changes} changes since the last message{last}: {', '.join(entry.actions)})"
        if entry.changes > 1
        else ""
    )
    servo = so101.servo_name(a.joint)
    # An alarm's own message is a sentence; cut, one beyond reason cannot take a whole SNS message alone
    # (the first alarm always goes in, and one over the limit would be refused at every flush).
    message = a.message if len(a.message) <= MESSAGE_TEXT_MAX else a.message[:MESSAGE_TEXT_MAX] + " ..."
    lines = [
        f"{a.severity.upper()} {a.action}: arm {a.device}, {servo}, {a.kind}{history}",
        f"  now {a.state}; value {value}{threshold}",
        f"  {message}",
    ]
    # While the alarm is up, or it rose since the last message (and maybe cleared already: the servo
    # still went through it); an acknowledged one needs nothing more done at the arm.
    # A servo error's bits: those of every raise since the last message, and the present ones while the
    # condition lasts (ACTIVE, ACKNOWLEDGED): advice for a voltage error raised, then gone, then an
    # overload, was the overload's alone.
    present = a.state in ("ACTIVE", "ACKNOWLEDGED")
    advice = what_to_do(a.kind, a.joint, _raised(entry.raised_value, a) if present else entry.raised_value)
    if (a.state == "ACTIVE" or "raised" in entry.actions) and advice:
        lines.append(f"  What to do: {advice}")
    lines += [
        f"  alarm id {a.alarm_id}, at {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime(a.at))}",
        "",
    ]
    return lines


def _raised(before: float | None, alert: Alert) -> float | None:
    """`alert`'s value joined to the raises' `before`: a servo error's status bits, or'ed together; any other
    kind's value as it is (its advice does not depend on it)."""
    now = alert.value
    if before is None or alert.kind != AlarmKind.SERVO_ERROR:
        return now
    if now is None or not math.isfinite(now):
        return before
    return float(int(before) | int(now)) if math.isfinite(before) else now


def _size(lines: list[str]) -> int:
    """The bytes `lines` take in a message body, as SNS counts them (UTF-8, a line break each)."""
    return sum(len(line.encode()) + 1 for line in lines)


# The fewest characters of a device id a shortened subject keeps: its first and last few, where ids of one
# fleet differ (arm-001, arm-002).
_DEVICE_MIN = 12


def _fit_device(head: str, device: str, tail: str) -> str:
    """head + device + tail, the device id shortened in its middle when the whole would pass SNS's 100
    characters: cut at the end, a long (valid, up to 64 characters) id pushed the servo out of the subject."""
    room = SUBJECT_MAX - len(head) - len(tail)
    if len(device) <= room or room < _DEVICE_MIN:
        return head + device + tail  # fits, or too little room to help: `_subject` cuts the end
    keep = room - 3
    return head + device[: keep - keep // 2] + "..." + device[len(device) - keep // 2 :] + tail


def _subject(text: str) -> str:
    """SNS's rules: printable ASCII, no line breaks, at most 100 characters."""
    clean = "".join(c if 32 <= ord(c) < 127 else "?" for c in text)
    return clean if len(clean) <= SUBJECT_MAX else clean[: SUBJECT_MAX - 3] + "..."


def sns_publisher(topic_arn: str, region: str = "", client: object = None) -> Publish:
    """`publish(subject, body)` to an SNS topic with boto3 (built on first use unless given)."""
    state: dict[str, object] = {"client": client}

    def publish(subject: str, body: str) -> None:
        sns = state["client"]
        if sns is None:
            import boto3  # noqa: PLC0415 - only an agent that sends alerts pays for boto3
            from botocore.config import Config  # noqa: PLC0415

            sns = boto3.client(
                "sns",
                region_name=region_or_env(region),
                config=Config(connect_timeout=5, read_timeout=10, retries={"max_attempts": 3}),
            )
            state["client"] = sns
        sns.publish(TopicArn=topic_arn, Subject=subject, Message=body)  # type: ignore[attr-defined]

    return publish
