"""REST access control and request-body limit, one ASGI middleware in front of every route.

With a token configured (COLONY_API_TOKEN / `colony server --token`) every mutating request
(POST, PUT, PATCH, DELETE) needs `Authorization: Bearer TOKEN`, compared in constant time;
reads need it too when COLONY_READ_OPEN=false. Always open: /healthz, /metrics and the
dashboard shell (/, /static/...), which holds no data and asks the user for the token. The
EventSource API cannot set headers, so a GET may carry the token as `?access_token=`.
A middleware rather than per-route dependencies so that a route added later is closed by
default. Bodies over the limit get 413 before any route reads them (docs/security.md).

Before the token, every request's Host must name this server (loopback, the bind address or
COLONY_ALLOWED_HOSTS: a DNS-rebinding page's name is none of them), and a mutating request
must not come from another site (its Origin, when sent, is the server's own; not
`Sec-Fetch-Site: cross-site`): a tokenless loopback server cannot be driven by a web page the
operator visits. After the body is read, a JSON body with NaN or Infinity (which Python's
parser accepts and JSON does not have) is a 422 before any route sees it.
"""

from __future__ import annotations

import email.message
import hmac
import ipaddress
import json
import math
import re
import socket
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np

from evorobotics.errors import EvoError
from evorobotics.evaluate import check_config, robot_steps
from schemas.run import RunConfig

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

MUTATING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
OPEN_PATHS = frozenset({"/healthz", "/metrics", "/", "/favicon.ico"})
OPEN_PREFIXES = ("/static/",)
DEFAULT_PORTS = {"http": 80, "https": 443}


def is_loopback(host: str) -> bool:
    """True for addresses only this machine reaches (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_bind(host: str, token: str | None) -> None:
    """ValueError (one line, with the fix) for a non-loopback bind without a token."""
    if token is None and not is_loopback(host):
        raise ValueError(
            f"refusing to listen on {host} without an API token: set COLONY_API_TOKEN or "
            "pass --token (or bind to 127.0.0.1)"
        )


def token_matches(expected: str, given: str | None) -> bool:
    """Constant-time comparison (hmac.compare_digest) of the configured and the given token."""
    if given is None:
        return False
    return hmac.compare_digest(expected.encode(), given.encode())


def allowed_hosts(bind_host: str, extra: Iterable[str]) -> frozenset[str] | None:
    """The host names (lower case, no port) a request's Host may give; None allows any (`*`).

    Loopback names are always allowed, and the bind address; a wildcard bind (0.0.0.0, ::)
    allows this machine's own host name too (IP literals are checked apart: `host_allowed`).
    """
    names = {name.strip().lower().strip("[]") for name in extra if name.strip()}
    if "*" in names:
        return None
    names |= {"localhost", bind_host.lower().strip("[]")}
    if bind_host in ("0.0.0.0", "::", ""):
        names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
    return frozenset(names)


def host_allowed(host: str, allowed: frozenset[str] | None, *, wildcard_bind: bool) -> bool:
    """Whether a Host header's name (port stripped) may reach this server.

    Loopback addresses always may; on a wildcard bind any IP literal may too, since a request
    reaches such a server by an address only when the address is its own (DNS rebinding needs
    a name the attacker controls)."""
    if allowed is None:
        return True
    name = _host_name(host)
    if name is None:
        return False
    if name in allowed or is_loopback(name):
        return True
    if wildcard_bind:
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return False
        return True
    return False


def _host_name(host: str) -> str | None:
    """`example.org:8000` -> `example.org`, `[::1]:8000` -> `::1`; None if malformed."""
    try:
        parsed = urlsplit(f"//{host}")
        name = parsed.hostname
        _ = parsed.port  # ValueError on a port that is not a number
    except ValueError:
        return None
    return name or None


def same_origin(origin: str, host: str, scheme: str) -> bool:
    """Whether an Origin header names the server the Host header names, by the request's
    scheme: the same scheme, host and port (default ports filled in)."""
    try:
        mine = urlsplit(f"{scheme}://{host}")
        theirs = urlsplit(origin)
        return (
            theirs.scheme == scheme
            and theirs.hostname is not None
            and theirs.hostname == mine.hostname
            and (theirs.port or DEFAULT_PORTS.get(scheme))
            == (mine.port or DEFAULT_PORTS.get(scheme))
        )
    except ValueError:
        return False


def _header(scope: Scope, wanted: bytes) -> str | None:
    for name, value in scope.get("headers", ()):
        if name == wanted:
            text: str = value.decode("latin-1")
            return text
    return None


class _NonFiniteError(ValueError):
    """A NaN or infinite number in a JSON body; its text is the token refused."""


def _refuse_constant(name: str) -> float:
    raise _NonFiniteError(name)


def _finite_float(text: str) -> float:
    value = float(text)
    if math.isinf(value):
        raise _NonFiniteError(text)  # e.g. 1e999, which Python's parser makes infinite
    return value


MAX_JSON_DEPTH = 64
"""Nesting of arrays and objects a JSON body may have: every model here nests a few levels,
and a deeper body would reach the parser's recursion limit (a 500) or waste its time."""
_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"')
_OPEN = np.zeros(256, dtype=np.int8)
_OPEN[[ord("["), ord("{")]] = 1
_OPEN[[ord("]"), ord("}")]] = -1


def json_depth(body: bytes) -> int:
    """How deep arrays and objects nest in a JSON text (brackets inside strings not counted);
    linear in C, so a body at the size limit costs milliseconds."""
    bare = _JSON_STRING.sub(b'""', body)
    steps = _OPEN[np.frombuffer(bare, dtype=np.uint8)]
    return int(np.cumsum(steps, dtype=np.int64).max(initial=0))


def non_finite_error(body: bytes) -> str | None:
    """Why a JSON body is refused (`NaN`, `Infinity`, `-Infinity` or an overflowing number),
    or None: malformed JSON is left to the route's own parser and its 422."""
    try:
        json.loads(body, parse_constant=_refuse_constant, parse_float=_finite_float)
    except _NonFiniteError as exc:
        return (
            f"body: {exc} is not a finite number (JSON has no NaN or Infinity; "
            "send a finite number or null)"
        )
    except ValueError:  # not JSON, or not UTF-8: the route says so
        return None
    return None


def _is_json(content_type: str | None) -> bool:
    """FastAPI's rule for parsing a body as JSON: no content type, or application/[*+]json."""
    if content_type is None:
        return True
    message = email.message.Message()
    message["content-type"] = content_type
    subtype = message.get_content_subtype()
    return message.get_content_maintype() == "application" and (
        subtype == "json" or subtype.endswith("+json")
    )


def _bearer(scope: Scope) -> str | None:
    for name, value in scope.get("headers", ()):
        if name == b"authorization":
            text: str = value.decode("latin-1")
            scheme, _, credentials = text.partition(" ")
            if scheme.lower() == "bearer" and credentials.strip():
                return credentials.strip()
            return None
    return None


def _query_token(scope: Scope) -> str | None:
    query: str = scope.get("query_string", b"").decode("latin-1")
    values: list[str] = parse_qs(query).get("access_token", [])
    return values[0] if values else None


async def _reply(
    send: Send, status: int, detail: str, headers: list[tuple[bytes, bytes]] | None = None
) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *(headers or []),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class SecurityMiddleware:
    """Host and Origin checks, bearer token, body-size limit and finite JSON numbers (pure
    ASGI, so event streams pass untouched)."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        token: str | None,
        read_open: bool,
        max_body_bytes: int,
        bind_host: str,
        extra_hosts: Iterable[str],
    ) -> None:
        if token is not None and not token.strip():
            raise ValueError("the API token must not be empty")
        if max_body_bytes < 1:
            raise ValueError(f"max_body_bytes must be >= 1, got {max_body_bytes}")
        self.app = app
        self.token = token
        self.read_open = read_open
        self.max_body_bytes = max_body_bytes
        self.hosts = allowed_hosts(bind_host, extra_hosts)
        self.wildcard_bind = bind_host in ("0.0.0.0", "::", "")

    def _foreign(self, scope: Scope) -> str | None:
        """Why a request from outside this server's own names or pages is refused, or None."""
        host = _header(scope, b"host")
        if host is None or not host_allowed(host, self.hosts, wildcard_bind=self.wildcard_bind):
            return (
                f"Host header {host!r} is not a name of this server: add it to COLONY_ALLOWED_HOSTS"
            )
        if scope["method"] not in MUTATING:
            return None
        origins = [v for k, v in scope.get("headers", ()) if k == b"origin"]
        if len(origins) > 1:
            return f"{len(origins)} Origin headers: a request has one origin, cross-site refused"
        origin = _header(scope, b"origin")
        if origin is not None and not same_origin(origin, host, scope.get("scheme", "http")):
            return f"Origin header {origin!r} is not this server's: cross-site requests refused"
        if _header(scope, b"sec-fetch-site") == "cross-site":
            return "Sec-Fetch-Site header is cross-site: cross-site requests refused"
        return None

    def _needs_token(self, method: str, path: str) -> bool:
        if self.token is None or path in OPEN_PATHS or path.startswith(OPEN_PREFIXES):
            return False
        return method in MUTATING or not self.read_open

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method = scope["method"]
        foreign = self._foreign(scope)
        if foreign is not None:
            await _reply(send, 403, foreign)
            return
        if self.token is not None and self._needs_token(method, scope["path"]):
            given = _bearer(scope)
            if given is None and method == "GET":
                given = _query_token(scope)
            if not token_matches(self.token, given):
                reason = "missing" if given is None else "invalid"
                await _reply(
                    send,
                    401,
                    f"{reason} API token: send 'Authorization: Bearer TOKEN' "
                    "(colony --token / COLONY_API_TOKEN)",
                    [(b"www-authenticate", b'Bearer realm="colony"')],
                )
                return
        for name, value in scope.get("headers", ()):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    await _reply(send, 400, "invalid Content-Length")
                    return
                if declared > self.max_body_bytes:
                    await self._too_large(send)
                    return
        await self._call_limited(scope, receive, send)

    async def _too_large(self, send: Send) -> None:
        await _reply(
            send, 413, f"request body larger than the limit of {self.max_body_bytes} bytes"
        )

    async def _call_limited(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Read the whole body first (at most the limit), then hand it to the app in one piece.

        Chunked bodies have no Content-Length, so they are counted as they arrive; nothing the
        route does runs before the size is known.
        """
        chunks: list[bytes] = []
        received = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client went away before the body was complete
            chunk = message.get("body", b"")
            received += len(chunk)
            if received > self.max_body_bytes:
                await self._too_large(send)
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        if body and _is_json(_header(scope, b"content-type")):
            depth = json_depth(body)
            refused = (
                f"body: JSON nested {depth} deep, more than the limit of {MAX_JSON_DEPTH}"
                if depth > MAX_JSON_DEPTH
                else non_finite_error(body)
            )
            if refused is not None:
                await _reply(send, 422, refused)
                return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


def run_limit_error(
    config: RunConfig,
    *,
    max_population_weights: int,
    max_generation_steps: int,
    max_run_steps: int,
) -> str | None:
    """Why the server refuses a run from a client (memory, CPU, a server file as maze), or None.

    RunConfig bounds each field; these bound the products, and `evaluate.check_config` (as
    `colony evolve` asks it) the maze: a shipped name, `gen:SIZE:SEED` or maze text (a bare
    path would read a file on the server) with room for the robot.
    """
    weights = config.network_spec.weight_count
    if config.population * weights > max_population_weights:
        return (
            f"population x weights = {config.population} x {weights} exceeds the server's "
            f"limit of {max_population_weights}"
        )
    try:
        check_config(config, files=False)
    except (ValueError, EvoError) as exc:
        return f"maze: {exc}"
    steps = robot_steps(config, config.population)
    if steps > max_generation_steps:
        return (
            f"population x trials x steps = {steps} exceeds the server's limit of "
            f"{max_generation_steps} robot steps per generation"
        )
    if steps * config.generations > max_run_steps:
        return (
            f"population x trials x steps x generations = {steps * config.generations} exceeds "
            f"the server's limit of {max_run_steps} robot steps per run (COLONY_MAX_RUN_STEPS)"
        )
    v = config.validation
    validation_steps = min(v.candidates, config.population) * v.poses * v.steps
    if validation_steps > max_generation_steps:
        return (
            f"validation candidates x poses x steps = {validation_steps} exceeds the server's "
            f"limit of {max_generation_steps} robot steps per generation"
        )
    return None
