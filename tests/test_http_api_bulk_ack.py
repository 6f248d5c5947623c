"""POST /alarms/ack, many alarms acknowledged in one request: the body checked whole before anything changes
(each refusal names the problem and the fix), each id's outcome answered in one 200, the state file written
once per request rather than once per alarm (a few hundred one by one took minutes), what it made kept over
an agent restart, and the same guard as the single acknowledgement (Origin, CSRF token)."""

from __future__ import annotations

import json
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_for
from twin.service.agent import AgentService
from twin.service.events import Event, EventQuery
from twin.service.http_api import BulkAckError, bulk_alarm_ids
from twin.service.shards import ACK_MANY_MAX

ARMS = ["arm-003", "arm-004"]  # with two workers, one on each (a listed fleet is dealt out in order)
WARM = "arm-003/elbow_flex/over_temperature"
HOT = "arm-003/elbow_flex/over_temperature_critical"
OTHER = "arm-004/elbow_flex/over_temperature"
UNKNOWN = "arm-009/elbow_flex/over_temperature"


# ------------------------------------------------------------------------------------------- the body


@pytest.mark.parametrize(
    ("body", "status", "error", "said"),
    [
        (b"arm-003/elbow_flex/overload", 400, "bad_json", "not JSON: send a JSON list of alarm ids"),
        (b'{"ids": ["a/b/c"]}', 400, "not_a_list", "a JSON dict: send a JSON list"),
        (b'"a/b/c"', 400, "not_a_list", "a JSON str"),
        (b'["a/b/c", 7]', 400, "bad_alarm_id", "item 1 (7) is not a string"),
        (b'["a/b/c", null]', 400, "bad_alarm_id", "item 1 (null) is not a string"),
        (b'["a/b/c", "d/e/f", "a/b/c"]', 400, "duplicate_alarm_id", "item 2 ('a/b/c') is listed twice"),
        (b"[" * 100_000, 400, "bad_json", "not JSON"),
        (
            json.dumps([f"arm-{i}/j/k" for i in range(ACK_MANY_MAX + 1)]).encode(),
            413,
            "too_many_alarm_ids",
            f"{ACK_MANY_MAX + 1} alarm ids, at most {ACK_MANY_MAX} per request: send them in chunks",
        ),
    ],
    ids=["text", "object", "string", "number", "null", "duplicate", "deep", "too-many"],
)
def test_a_body_that_is_not_a_list_of_distinct_ids_is_refused_naming_the_fix(
    body: bytes, status: int, error: str, said: str
) -> None:
    with pytest.raises(BulkAckError) as caught:
        bulk_alarm_ids(body)
    assert (caught.value.status, caught.value.error) == (status, error)
    assert said in str(caught.value), str(caught.value)


def test_a_list_of_distinct_ids_is_taken_in_its_order() -> None:
    assert bulk_alarm_ids(b"[]") == ()
    ids = [f"arm-{i}/elbow_flex/overload" for i in range(ACK_MANY_MAX)]
    assert bulk_alarm_ids(json.dumps(ids[::-1]).encode()) == tuple(ids[::-1])


# ------------------------------------------------------------------------------------------- an agent


def post(url: str, body: bytes, headers: dict[str, str] | None = None) -> tuple[int, dict[str, Any]]:
    request = urllib.request.Request(url + "/alarms/ack", data=body, method="POST", headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=30) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read())


def http_get_html(url: str) -> tuple[int, str, bytes]:
    request = urllib.request.Request(url, headers={"Accept": "text/html"})
    with urllib.request.urlopen(request, timeout=30) as resp:
        return resp.status, resp.headers.get("Content-Type", ""), resp.read()


def hot_agent(state_file: Path, workers: int, **overrides: Any) -> AgentService:
    from test_alerts import hot_arm_settings
    from twin.service.config import load_config

    settings = hot_arm_settings(
        **{"twin.state_file": str(state_file), "telemetry.devices": ARMS, **overrides}
    )
    agent = AgentService(load_config(None, settings), workers=workers)
    agent.start()
    return agent


def states(agent: AgentService) -> dict[str, str]:
    return {a.alarm_id: a.state for a in agent.alarms(include_normal=True)}


def heat(agent: AgentService, ids: tuple[str, ...], temp: float = 68, state: str = "ACTIVE") -> None:
    """Both arms' elbows at `temp` C until every alarm of `ids` is in `state` (at 68 C the warning and the
    critical are ACTIVE)."""
    from test_alerts import hot

    def reached() -> bool:
        for device in ARMS:
            agent.feed(f"dt/lerobot/{device}/telemetry", hot(device, int(time.time() * 1000), temp))
        now = states(agent)
        return all(now.get(a) == state for a in ids)

    wait_for(reached, 60, f"{ids} {state}", interval=0.2)


@pytest.fixture(params=[1, 2], ids=["in-process", "two-worker-processes"])
def workers(request: pytest.FixtureRequest) -> int:
    return int(request.param)


@pytest.fixture
def agent(tmp_path: Path, workers: int) -> Iterator[AgentService]:
    agent = hot_agent(tmp_path / "state.json", workers)
    try:
        yield agent
    finally:
        agent.stop()


@pytest.mark.slow
def test_many_alarms_are_acknowledged_in_one_request_and_one_write_kept_over_a_restart(
    tmp_path: Path, agent: AgentService, workers: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each id's outcome in the order sent, an already acknowledged one and an unknown one among them (no
    refusal of the whole); the state file written once for the request, before its answer; and an agent
    started again on that file has them acknowledged."""
    heat(agent, (WARM, HOT, OTHER))
    status, body = post(agent.http_url, json.dumps([WARM]).encode())
    assert status == 200 and body["results"][0]["state"] == "ACKNOWLEDGED", body
    # The writes the request makes; the supervisor's own (every second, on its thread) are not counted.
    state_file = agent._state_file
    assert state_file is not None
    saves: list[str] = []
    real_save = state_file.save

    def save(*args: Any, **kwargs: Any) -> None:
        if threading.current_thread().name != "twin-supervisor":
            saves.append(threading.current_thread().name)
        real_save(*args, **kwargs)

    monkeypatch.setattr(state_file, "save", save)
    status, body = post(agent.http_url, json.dumps([OTHER, UNKNOWN, WARM, HOT]).encode())
    assert status == 200, body
    got = [(r["alarm_id"], r["outcome"], r["state"]) for r in body["results"]]
    assert got == [
        (OTHER, "acknowledged", "ACKNOWLEDGED"),
        (UNKNOWN, "alarm_not_found", None),
        (WARM, "nothing_to_acknowledge", "ACKNOWLEDGED"),
        (HOT, "acknowledged", "ACKNOWLEDGED"),
    ], body
    assert "is ACKNOWLEDGED" in body["results"][2]["detail"], body
    assert "no alarm has this id" in body["results"][1]["detail"], body  # as one acknowledgement's 404 says
    assert body["counts"] == {
        "acknowledged": 2,
        "nothing_to_acknowledge": 1,
        "alarm_not_found": 1,
        "worker_unavailable": 0,
    }, body
    assert len(saves) == 1, saves
    kept = {a["alarm_id"]: a["state"] for a in json.loads(state_file.path.read_text())["alarms"]}
    assert {k: kept.get(k) for k in (WARM, HOT, OTHER)} == dict.fromkeys((WARM, HOT, OTHER), "ACKNOWLEDGED")

    # Each is recorded as its own event, as a single acknowledgement is.
    def acked() -> list[Event] | None:
        found = agent.events(EventQuery(kinds=frozenset({"alarm"}), limit=1000))
        mine = [e for e in found if "acknowledged by a person" in e.message]
        return mine if len(mine) >= 3 else None

    recorded = wait_for(acked, 30, "an event for each acknowledgement")
    assert sorted(e.device for e in recorded) == ["arm-003", "arm-003", "arm-004"], recorded
    agent.stop()
    again = hot_agent(state_file.path, workers)
    try:
        wanted = dict.fromkeys((WARM, HOT, OTHER), "ACKNOWLEDGED")
        wait_for(
            lambda: {k: states(again).get(k) for k in wanted} == wanted,
            30,
            "the acknowledgements back after the restart",
            interval=0.1,
        )
    finally:
        again.stop()


@pytest.mark.slow
def test_one_acknowledgement_of_a_cleared_alarm_says_it_is_cleared(tmp_path: Path, workers: int) -> None:
    """The single acknowledgement's 409 told a NORMAL alarm in the words of one acknowledged already; it
    names the alarm and its state, and a NORMAL one is said to have cleared (through a worker process too)."""
    from test_servo_alarms_e2e import post as post_once  # one POST with no body, its status and JSON

    agent = hot_agent(tmp_path / "state.json", workers, **{"alarms.temperature_clear_after_s": 0.0})
    try:
        heat(agent, (WARM,))
        url = f"{agent.http_url}/alarms/{WARM}/ack"
        status, body = post_once(url)
        assert status == 200 and body["alarms"][0]["state"] == "ACKNOWLEDGED", body
        status, body = post_once(url)
        assert (status, body["error"], body["state"], body["alarm_id"]) == (
            409,
            "nothing_to_acknowledge",
            "ACKNOWLEDGED",
            WARM,
        ), body
        assert "already cleared" not in body["detail"], body
        heat(agent, (WARM,), temp=35, state="NORMAL")
        status, body = post_once(url)
        assert (status, body["error"], body["state"], body["alarm_id"]) == (
            409,
            "nothing_to_acknowledge",
            "NORMAL",
            WARM,
        ), body
        assert f"alarm {WARM} is NORMAL, already cleared: " in body["detail"], body
    finally:
        agent.stop()


@pytest.mark.slow
def test_a_refused_bulk_request_changes_nothing(agent: AgentService) -> None:
    """A bad body, a browser's request from another origin or without the console's token, and more ids than
    the limit: each refused whole, with a clear status, and every alarm still ACTIVE after."""
    heat(agent, (WARM, HOT))
    url = agent.http_url
    origin = url.removesuffix("/")
    status, _, html = http_get_html(url + "/")
    assert status == 200
    token = html.decode().split('name="csrf-token" content="', 1)[1].split('"', 1)[0]
    ids = json.dumps([WARM, HOT]).encode()
    too_many = [f"x-{i}/j/k" for i in range(ACK_MANY_MAX)]
    refused = [
        (post(url, json.dumps([WARM, HOT, WARM]).encode()), 400, "duplicate_alarm_id"),
        (post(url, json.dumps([WARM, 3]).encode()), 400, "bad_alarm_id"),
        (post(url, json.dumps({"ids": [WARM]}).encode()), 400, "not_a_list"),
        (post(url, json.dumps([WARM, *too_many]).encode()), 413, "too_many_alarm_ids"),
        (post(url, ids, {"Origin": "http://evil.example", "X-CSRF-Token": token}), 403, "origin_not_allowed"),
        (post(url, ids, {"Origin": origin}), 403, "csrf_token_missing"),
        (post(url, ids, {"Origin": origin, "X-CSRF-Token": "stale"}), 403, "csrf_token_invalid"),
        (post(url, ids, {"Sec-Fetch-Site": "cross-site"}), 403, "cross_site"),
    ]
    for (status, body), want_status, want_error in refused:
        assert (status, body["error"]) == (want_status, want_error), body
        assert body["detail"], body
    now = states(agent)
    assert (now[WARM], now[HOT]) == ("ACTIVE", "ACTIVE"), now
    # An empty list is no mistake (a script posting the waiting ids when none wait): 200, every count 0.
    status, body = post(url, b"[]")
    assert status == 200 and set(body["counts"].values()) == {0}, body
    # The console's own request: its origin and its token.
    status, body = post(url, ids, {"Origin": origin, "Sec-Fetch-Site": "same-origin", "X-CSRF-Token": token})
    assert status == 200 and body["counts"]["acknowledged"] == 2, body


def test_the_console_sends_at_most_what_one_request_takes() -> None:
    """The console chunks its ids by its own copy of the limit: a larger one had every chunk refused."""
    from twin.service.console import ASSETS

    script = (Path(ASSETS) / "common.js").read_text()
    assert f"const ACK_MANY_MAX = {ACK_MANY_MAX};" in script


@pytest.mark.slow
def test_every_worker_is_asked_before_any_answer_is_awaited(tmp_path: Path) -> None:
    """With two worker processes each takes its share and its checkpoint at the same time: the agent sends
    both requests before it waits for either (asked one by one, a request held the keep lock for the sum
    of the workers' checkpoints)."""
    agent = hot_agent(tmp_path / "state.json", 2)
    try:
        heat(agent, (WARM, OTHER))
        seen: list[tuple[str, int]] = []
        for shard in agent._shards:
            real = shard.request

            def request(req: Any, real: Any = real, index: int = shard.index) -> Any:
                wait = real(req)
                if type(req).__name__ != "AckManyRequest":
                    return wait
                seen.append(("asked", index))

                def waited() -> Any:
                    seen.append(("awaited", index))
                    return wait()

                return waited

            shard.request = request  # type: ignore[method-assign]
        status, body = post(agent.http_url, json.dumps([WARM, OTHER]).encode())
        assert status == 200 and body["counts"]["acknowledged"] == 2, body
        assert [what for what, _ in seen] == ["asked", "asked", "awaited", "awaited"], seen
        assert {index for _, index in seen} == {0, 1}, seen
    finally:
        agent.stop()
