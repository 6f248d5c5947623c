"""Broker settings: where and how the agent, the edge simulator and the benchmark connect.

`BrokerConfig` is the agent config's `[broker]` section itself (as `HealthThresholds` is `[health]`), so a
setting is defined, defaulted and validated once, whether it comes from TOML, a flag or code. Pure standard
library: loading a config never imports awscrt (`twin.transport.client` builds the client).
"""

from __future__ import annotations

import re
import secrets
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

# Every agent's client ids start with this, then a name of its own (`agent_client_id_prefix`): the stack's
# name for the twin host (stacks/twin_stack.py renders it into the host's config and scopes the IAM policy
# to it), the machine's host name for any other agent (a laptop), unless the config gives one. The shared
# subscription's group is the prefix too (twin.transport.plan.shared_group), so two agents never split a
# fleet's messages between them, and never reuse each other's client ids.
DEFAULT_CLIENT_ID_PREFIX = "so101-twin-"
IOT = "iot"
SCHEME_PORTS: dict[str, int] = {"mqtt": 1883, "mqtts": 8883}
IOT_PORT = 443  # IoT Core over WebSocket (SigV4)
# IoT Core refuses client ids over 128 bytes; the random suffix takes 12.
CLIENT_ID_PREFIX_MAX = 100
_CLIENT_ID_PREFIX_RE = re.compile(r"^[A-Za-z0-9_.:-]+$")
_NOT_IN_CLIENT_ID = re.compile(r"[^A-Za-z0-9_.:-]+")
# IoT Core allows a keep-alive of at most 1200 s.
KEEP_ALIVE_RANGE_S = (5, 1200)
# Beyond this many connections a fleet wants an IoT rule to Kinesis instead (docs/aws-facts.md).
MAX_CONNECTIONS_LIMIT = 64


class BrokerConfigError(ValueError):
    """A broker setting is invalid; the message names the setting (`broker.<key>`), the value and the fix."""


@dataclass(frozen=True)
class BrokerConfig:
    """`url`: "iot" (AWS IoT Core, SigV4 WebSocket), "mqtt://host:port" or "mqtts://host:port"."""

    url: str = IOT
    region: str = ""
    endpoint: str = ""
    # Empty: this machine's own, `so101-twin-<host name>-` (agent_client_id_prefix).
    client_id_prefix: str = ""
    ca_file: str = ""
    # Reconnect backoff. awscrt doubles the delay after each failed attempt up to the maximum, and FULL
    # jitter waits a uniform random time in [0, current delay]. So once a broker is back, the next attempt
    # comes at most max_reconnect_delay_ms later: 2000 ms keeps "telemetry flows again within 3 s of the
    # broker's return" true even after a long outage, while averaging one attempt per second per agent,
    # which is IoT Core's CONNECT limit per client id. 250 ms minimum: a blip (broker restart) costs little.
    min_reconnect_delay_ms: int = 250
    max_reconnect_delay_ms: int = 2000
    # The builder default is 1200 s; a NAT or network cut that drops packets silently would then go unnoticed
    # for up to half an hour. 30 s detects it within ~45 s for a negligible ping cost.
    keep_alive_s: int = 30
    # Publishes per second one connection may carry. IoT Core delivers at most 100 per connection, inbound
    # plus outbound, and discards the rest silently; 0 = the broker's own: 100 on "iot", unlimited elsewhere.
    # The connection pool (twin.transport.pool) plans to use 80 % of it.
    per_connection_limit: int = 0
    # The most connections a whole-fleet ("*") subscription may grow to under that budget.
    max_connections: int = 8

    def __post_init__(self) -> None:
        # Surrounding spaces (a hand-edited TOML value, a shell variable) are not part of a URL.
        object.__setattr__(self, "url", (self.url or "").strip())
        if not self.client_id_prefix:
            object.__setattr__(self, "client_id_prefix", agent_client_id_prefix(socket.gethostname()))
        self._check_url()
        self._check_client_id_prefix()
        if self.ca_file and self.kind != "mqtts":
            raise BrokerConfigError(
                f"broker.ca_file = {self.ca_file!r} is set but broker.url = {self.url!r}: a private CA only "
                "applies to mqtts:// (IoT Core uses the system trust store); clear ca_file or use mqtts://"
            )
        if self.ca_file and not Path(self.ca_file).is_file():
            raise BrokerConfigError(
                f"broker.ca_file = {self.ca_file!r} does not exist; give the PEM CA bundle that signed the "
                "broker's certificate, or leave it empty"
            )
        if not 0 < self.min_reconnect_delay_ms <= self.max_reconnect_delay_ms:
            raise BrokerConfigError(
                f"reconnect delays must satisfy 0 < min ({self.min_reconnect_delay_ms} ms) <= max "
                f"({self.max_reconnect_delay_ms} ms); fix broker.min_reconnect_delay_ms / "
                "broker.max_reconnect_delay_ms"
            )
        if self.per_connection_limit < 0:
            raise BrokerConfigError(
                f"broker.per_connection_limit = {self.per_connection_limit} must be 0 (the broker's own: 100 "
                "publishes/s on IoT Core, unlimited elsewhere) or a positive number of publishes per second"
            )
        if not 1 <= self.max_connections <= MAX_CONNECTIONS_LIMIT:
            raise BrokerConfigError(
                f"broker.max_connections = {self.max_connections} is outside 1..{MAX_CONNECTIONS_LIMIT}; it "
                "bounds the connections a whole-fleet subscription grows to (each carries "
                "per_connection_limit)"
            )
        lo, hi = KEEP_ALIVE_RANGE_S
        if not lo <= self.keep_alive_s <= hi:
            raise BrokerConfigError(
                f"broker.keep_alive_s = {self.keep_alive_s} is outside {lo}..{hi} (IoT Core allows at most "
                f"{hi} s)"
            )

    def _check_url(self) -> None:
        url = self.url
        if not url:
            raise BrokerConfigError(
                'broker.url is empty: use "iot" (AWS IoT Core), "mqtt://host:port" or "mqtts://host:port"'
            )
        if url == IOT:
            return
        parts = urlsplit(url)
        if parts.scheme not in SCHEME_PORTS or not parts.hostname:
            raise BrokerConfigError(
                f'broker.url = {url!r} is not a broker: use "iot" (AWS IoT Core), "mqtt://host:port" '
                '(plain TCP) or "mqtts://host:port" (TLS)'
            )
        if parts.path not in ("", "/") or parts.query or parts.username:
            raise BrokerConfigError(
                f"broker.url = {url!r} has a path, query or credentials; give only mqtt[s]://host:port"
            )
        try:
            _ = parts.port
        except ValueError as exc:
            raise BrokerConfigError(
                f"broker.url = {url!r} has a bad port ({exc}); use a number 1..65535, "
                "e.g. mqtt://127.0.0.1:1883"
            ) from None

    def _check_client_id_prefix(self) -> None:
        prefix = self.client_id_prefix
        if len(prefix) > CLIENT_ID_PREFIX_MAX or not _CLIENT_ID_PREFIX_RE.match(prefix):
            raise BrokerConfigError(
                f"broker.client_id_prefix = {prefix!r} must be 1..{CLIENT_ID_PREFIX_MAX} characters of "
                "letters, digits and _ . : - (the IAM policy matches client ids by this prefix)"
            )

    @property
    def kind(self) -> str:
        """ "iot", "mqtt" or "mqtts"."""
        return IOT if self.url == IOT else urlsplit(self.url).scheme

    @property
    def host(self) -> str:
        if self.kind == IOT:
            return self.endpoint
        return urlsplit(self.url).hostname or ""

    @property
    def port(self) -> int:
        if self.kind == IOT:
            return IOT_PORT
        parts = urlsplit(self.url)
        return parts.port or SCHEME_PORTS[parts.scheme]

    def where(self) -> str:
        """Where this connects, for log lines and errors."""
        return self.url if self.kind != IOT else f"IoT Core ({self.region or 'default region'})"


# What to do when no AWS credentials are found for IoT Core (the default chain: the environment, the AWS
# profile, the instance role).
NO_CREDENTIALS_HINT = (
    "No AWS credentials were found: on a laptop run `aws configure` or `aws sso login`, or set AWS_PROFILE "
    "(or AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY); on the twin host the instance role gives them (is its "
    "instance profile attached?). For a local broker instead, give --broker mqtt://127.0.0.1:1883"
)


def crt_error_text(error: BaseException | None) -> str:
    """awscrt's error as text to go inside a sentence: its message ends with a full stop, which put
    "refused.; retrying" and "refused.. Is a broker ..." in the lines around it."""
    return str(error).rstrip(" .")


def connack_code(data: Any) -> int | None:
    """The reason code of a failed connect's CONNACK (awscrt's LifecycleConnectFailureData), None without
    one: it says more than awscrt's error, which says only that the CONNACK was not a success."""
    reason = getattr(getattr(data, "connack_packet", None), "reason_code", None)
    return None if reason is None else int(reason)


def failure_hint(config: BrokerConfig, data: Any) -> str:
    """What to check after a failed connect: the CONNACK's refusal, else what awscrt's error names."""
    return connack_hint(config, connack_code(data)) or connect_hint(config, data.exception)


def connect_hint(config: BrokerConfig, error: BaseException | None) -> str:
    """What to check after a failed connect, when awscrt's error (named, not fixed) says what went wrong;
    "" when there is nothing more to say than the error."""
    name = getattr(error, "name", "")
    if config.kind == IOT and name.startswith("AWS_AUTH_SIGNING_NO_CREDENTIALS"):
        return NO_CREDENTIALS_HINT
    # Only a refusal is certain: nothing listens there. IoT Core always listens: its problems are elsewhere.
    if name != "AWS_IO_SOCKET_CONNECTION_REFUSED" or config.kind == IOT:
        return ""
    return (
        f"Is a broker listening on {config.host} port {config.port} (a local one: `mosquitto -p "
        f"{config.port}`)? Else fix the URL in --broker or [broker] url"
    )


# CONNACK reason codes that refuse who the client is (MQTT 5, section 3.2.2.2): its client id, its
# credentials, or what it is allowed.
CONNACK_REFUSALS = {
    133: "client identifier not valid",
    134: "bad user name or password",
    135: "not authorized",
    138: "banned",
}


def connack_hint(config: BrokerConfig, reason: int | None) -> str:
    """The refusal a CONNACK's reason code names, and what to check; "" for any other reason (or none)."""
    said = CONNACK_REFUSALS.get(reason) if reason is not None else None
    if said is None:
        return ""
    if config.kind == IOT:
        # IoT Core authorises a SigV4 connect by the role's iot:Connect on client/<client id>; the stack
        # allows exactly the pool indexes its settings plan (docs/scaling.md, "The stack's limits").
        return (
            f"IoT Core refused the connection ({said}, CONNACK reason {reason}): the role does not allow "
            "this client id. On the twin host the role allows the connections the stack's settings plan "
            "(maxConnections for the whole fleet; the listed arms at armRateHz): a [broker] "
            "max_connections, per_connection_limit or [health] expected_rate_hz in agent.local.toml that "
            "plans more is refused so. Take those keys out, or change the settings in twin.settings.toml "
            "and deploy"
        )
    return (
        f"the broker refused the connection ({said}, CONNACK reason {reason}): its authentication or access "
        "rules do not admit this client (mosquitto: allow_anonymous, password_file, acl_file)"
    )


def agent_client_id_prefix(name: str) -> str:
    """`so101-twin-<name>-`, the client id prefix (and shared-subscription group) of the agent `name` stands
    for: a stack's name, a host name. Characters a client id may not hold become '-'; long names are cut so
    the prefix stays within CLIENT_ID_PREFIX_MAX."""
    room = CLIENT_ID_PREFIX_MAX - len(DEFAULT_CLIENT_ID_PREFIX) - 1
    safe = _NOT_IN_CLIENT_ID.sub("-", name).strip("-_.:")[:room].strip("-_.:") or "agent"
    return f"{DEFAULT_CLIENT_ID_PREFIX}{safe}-"


def new_client_id(prefix: str) -> str:
    """prefix + 12 random hex digits: unique per process, since two clients with one id evict each other."""
    return f"{prefix}{secrets.token_hex(6)}"
