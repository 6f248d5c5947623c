"""Who may ask the agent's HTTP server what: the Host allow-list, the body limit, and the rules for requests
that change state (loopback clients only; a browser's request only from the console's own origin and with
its CSRF token).

The API has no authentication and listens on loopback: what it must keep out is a web page in a browser on
the same host (the DCV desktop's) that talks to 127.0.0.1 behind the operator's back:
- A page of another site cannot read our answers (same-origin policy), unless it points its own host name at
  127.0.0.1 (DNS rebinding): then its requests carry its own name in `Host`, which the allow-list refuses.
- A page of another site can still *send* a POST (a form, `fetch` with `no-cors`). A browser marks such a
  request with `Origin` (and `Sec-Fetch-Site`); one whose origin is not this server is refused, and one that
  is must carry the CSRF token the console's pages embed, which another origin cannot read.
- curl, `twin` and scripts on the host send neither header; they acknowledge as before, from loopback only.

Pure ASGI middleware (no per-request objects beyond the header scan), so it costs next to nothing on the
`/stream` and `/state` paths.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import logging
import secrets
from collections.abc import Iterable
from dataclasses import dataclass
from urllib.parse import urlsplit

from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger(__name__)

# The names every browser and tool uses for this host's loopback interface; IP literals in 127.0.0.0/8 and
# ::1 are accepted as such.
LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"})
CSRF_HEADER = "x-csrf-token"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


def is_loopback_client(address: str) -> bool:
    """True for a loopback peer: 127.0.0.0/8, ::1, and IPv4 loopback seen through a dual-stack socket
    (::ffff:127.0.0.1). Anything unparsable is not loopback."""
    try:
        ip = ipaddress.ip_address(address.split("%", 1)[0])
    except ValueError:
        return False
    mapped = getattr(ip, "ipv4_mapped", None)
    return (mapped or ip).is_loopback


def host_name(host_header: str) -> str:
    """The name part of a Host header value (`[::1]:8080` -> `::1`, `Example.com.:80` -> `example.com`). A
    port must be digits: otherwise (`127.0.0.1:80@evil.example`) the whole value is the name, which no rule
    allows, rather than the part before the colon."""
    value = host_header.strip().lower()
    if value.startswith("["):
        address, _, port = value[1:].partition("]")
        return address if port == "" or (port[:1] == ":" and port[1:].isdigit()) else value
    if value.count(":") == 1:
        name, _, port = value.partition(":")
        if not port.isdigit():
            return value
        value = name
    return value.rstrip(".")


def host_allowed(name: str, extra: frozenset[str]) -> bool:
    if name in LOOPBACK_NAMES or name in extra:
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class GuardSettings:
    """`allowed_hosts`: names (or IP literals) accepted in `Host` besides the loopback ones, without ports.
    `max_body_bytes`: the largest request body accepted."""

    allowed_hosts: frozenset[str] = frozenset()
    max_body_bytes: int = 65536

    @classmethod
    def of(cls, allowed_hosts: Iterable[str], max_body_bytes: int, bound_host: str = "") -> GuardSettings:
        names = {host_name(h) for h in allowed_hosts if h.strip()}
        # A server told to listen on one specific address answers to that address too.
        if bound_host and bound_host not in ("0.0.0.0", "::", ""):
            names.add(host_name(bound_host if ":" not in bound_host else f"[{bound_host}]"))
        return cls(allowed_hosts=frozenset(names), max_body_bytes=max_body_bytes)


def new_csrf_token() -> str:
    return secrets.token_urlsafe(32)


class RequestGuard:
    """The ASGI middleware (module doc). `csrf_token` is the one the console's pages carry."""

    def __init__(self, app: ASGIApp, settings: GuardSettings, csrf_token: str) -> None:
        self.app = app
        self.settings = settings
        self.csrf_token = csrf_token
        self.refused: dict[str, int] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = _headers(scope)
        refusal = self._check(scope, headers)
        if refusal is not None:
            status, error, detail = refusal
            self.refused[error] = self.refused.get(error, 0) + 1
            log.info("http request refused: %s", error, extra={"path": scope.get("path"), "detail": detail})
            await _send_json(send, status, {"error": error, "detail": detail})
            return
        if scope["method"] in SAFE_METHODS:
            await self.app(scope, receive, send)
            return
        await self.app(scope, _limited(receive, self.settings.max_body_bytes), send)

    def _check(self, scope: Scope, headers: dict[str, str]) -> tuple[int, str, str] | None:
        host = headers.get("host")
        if host is not None and not host_allowed(host_name(host), self.settings.allowed_hosts):
            return (
                400,
                "host_not_allowed",
                f"Host {host!r} is not one this agent answers to (loopback names, and [http] allowed_hosts "
                "in its config); a page that reached it under another name is refused",
            )
        if scope["method"] in SAFE_METHODS:
            return _isolated(headers)
        length = headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > self.settings.max_body_bytes):
            return (
                413,
                "body_too_large",
                f"request body of {length} bytes is over the {self.settings.max_body_bytes}-byte limit "
                "([http] max_body_bytes)",
            )
        client = scope.get("client")
        address = client[0] if client else ""
        if not is_loopback_client(address):
            return (
                403,
                "forbidden",
                f"changing state (acknowledging alarms, forgetting arms) is allowed from this host only "
                f"(loopback), not {address}; open a shell on the host (the stack's SsmSessionCommand) and "
                "ask there",
            )
        return self._browser_check(headers, host)

    def _browser_check(self, headers: dict[str, str], host: str | None) -> tuple[int, str, str] | None:
        origin = headers.get("origin")
        fetch_site = headers.get("sec-fetch-site")
        if origin is None and fetch_site is None:
            return None  # not a browser: curl, `twin`, a script on the host
        if origin is not None and not _same_origin(origin, host):
            return (
                403,
                "origin_not_allowed",
                f"a browser request from origin {origin!r} may not change state here; only the console's "
                "own pages may",
            )
        if fetch_site is not None and fetch_site.lower() not in ("same-origin", "none"):
            return (403, "cross_site", f"a {fetch_site} browser request may not change state here")
        token = headers.get(CSRF_HEADER, "")
        if not token:
            return (
                403,
                "csrf_token_missing",
                f"a browser request that changes state must carry the console's CSRF token in "
                f"{CSRF_HEADER!r}; reload the console page",
            )
        if not hmac.compare_digest(token.encode(), self.csrf_token.encode()):
            return (403, "csrf_token_invalid", "the CSRF token does not match; reload the console page")
        return None


def _isolated(headers: dict[str, str]) -> tuple[int, str, str] | None:
    """A page of another origin may link to the console (a navigation), not fetch from it: a walk's page
    elsewhere could have a browser on the host pull session files, exports and streams from 127.0.0.1
    (unread, but each costs the agent its work, and a stream one of the browser's six connections). That
    includes another port of the same host (`same-site` to a browser): nothing of ours fetches across
    ports, and a walk's page served there had the agent build session plots for it. Only a browser says
    where a request comes from; curl and `twin` send no `Sec-Fetch-Site` and pass."""
    if headers.get("sec-fetch-site", "").lower() not in ("cross-site", "same-site"):
        return None
    mode, dest = headers.get("sec-fetch-mode", "").lower(), headers.get("sec-fetch-dest", "").lower()
    if mode == "navigate" and dest in ("document", ""):
        return None  # a link followed, from an alarm e-mail in a webmail or another site's page
    return (
        403,
        "cross_site",
        f"a page of another origin may not fetch from this agent ({mode or 'no mode'} request for "
        f"{dest or 'no destination'}); open the console itself",
    )


def _same_origin(origin: str, host: str | None) -> bool:
    if host is None or origin == "null":
        return False
    parts = urlsplit(origin)
    return parts.scheme in ("http", "https") and parts.netloc.lower() == host.strip().lower()


def _headers(scope: Scope) -> dict[str, str]:
    # Latin-1 is what HTTP header bytes decode as; the last of repeated headers wins (none we read repeat).
    return {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"]}


class BodyTooLarge(Exception):  # noqa: N818 - reads as the answer it becomes (413)
    """A chunked body grew past the limit while it was read."""


def _limited(receive: Receive, limit: int) -> Receive:
    """`receive` that counts the body (a chunked one has no Content-Length to check first)."""
    seen = 0

    async def counted() -> Message:
        nonlocal seen
        message = await receive()
        if message["type"] == "http.request":
            seen += len(message.get("body", b""))
            if seen > limit:
                raise BodyTooLarge(f"request body over the {limit}-byte limit ([http] max_body_bytes)")
        return message

    return counted


async def _send_json(send: Send, status: int, payload: dict[str, object]) -> None:
    body = json.dumps(payload).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"cache-control", b"no-store"),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})
