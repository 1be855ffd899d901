"""Security shared by the server, workers and robot agents (docs/security.md).

One module on purpose: both ends of a signed push must build the very same bytes, and every
zenoh client (worker, agent) adds the same authentication keys. It depends on the standard
library alone; the Ed25519 code itself lives in server/robots/signing.py (sign) and
robot_agent/verify.py (verify), which import `cryptography`.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path

# ------------------------------------------------------------------ limits (docs/security.md)

MAX_BODY_BYTES = 1 << 20
"""REST request bodies (the largest legitimate one, a RunConfig with a 4 KiB maze, is ~6 KiB)."""
MAX_POPULATION_WEIGHTS = 8_000_000
"""population x weights of one run: its genomes are 64 MB of float64 (paper: 100 x 7104)."""
MAX_GENERATION_STEPS = 50_000_000
"""population x trials x steps: robot steps of one generation (paper: 100 x 3 x 40 = 12,000)."""
MAX_RUN_STEPS = 100_000_000_000
"""population x trials x steps x generations: robot steps of one run's training (the default
run: 25 M; 10^11 is hours of a few dozen cores)."""
MAX_ZENOH_MESSAGE = 128 << 20
"""zenoh messages the server's router accepts (transport/link/rx/max_message_size)."""
MAX_ROBOT_MESSAGE = 32 << 20
"""A robot control message as bytes (a push of a 1M-weight controller document is ~20 MB)."""
MAX_TRACE_BYTES = 4 << 20
"""A trace batch as bytes (600 samples are ~25 KB)."""
MAX_TRACE_SAMPLES = 10_000
"""Samples in one trace batch (the agent sends at most 600)."""

# ------------------------------------------------------------------ zenoh authentication and TLS


def _json5(value: object) -> str:
    return json.dumps(value)


@dataclass(frozen=True)
class ZenohClientAuth:
    """What a zenoh client (worker, agent) adds to its config: user/password and a TLS root CA."""

    user: str | None = None
    password: str | None = None
    root_ca: Path | None = None
    """PEM of the CA that signed the router's certificate (for tls/ endpoints)."""

    def __post_init__(self) -> None:
        if (self.user is None) != (self.password is None):
            raise ValueError("zenoh user and password go together: give both or neither")
        if self.user is not None and (":" in self.user or not self.user):
            raise ValueError(f"zenoh user must be non-empty without ':', got {self.user!r}")

    def entries(self) -> list[tuple[str, str]]:
        """(key, json5 value) pairs for `zenoh.Config.insert_json5`."""
        out: list[tuple[str, str]] = []
        if self.user is not None:
            out.append(
                ("transport/auth/usrpwd", _json5({"user": self.user, "password": self.password}))
            )
        if self.root_ca is not None:
            out.append(("transport/link/tls/root_ca_certificate", _json5(str(self.root_ca))))
        return out


_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,128}$")
"""A zenoh user of a role is a worker or robot name (one key chunk; schemas.wire.NAME_PATTERN)."""
_ROBOT_KEYS = ("alive", "command", "ack", "traces", "replace")
_SERVER_JOB_QUERYABLES = ("evocolony/jobs/next/*", "evocolony/jobs/result/*")
_SERVER_ROBOT_QUERYABLES = ("evocolony/robots/*/traces", "evocolony/robots/*/replace")
"""The server's queryables (schemas.wire / schemas.robots KEY_*): their declarations must reach
the clients that ask them, or a querier, and a query with target ALL, finds no answerer."""


def _allow(rule: str, messages: list[str], flow: str, keys: list[str]) -> dict[str, object]:
    return {
        "id": rule,
        "messages": messages,
        "flows": [flow],
        "permission": "allow",
        "key_exprs": keys,
    }


ROLES = ("workers", "robots", "trackers")
"""The keys of a zenoh roles file, in `ZenohRoles`' field order."""


@dataclass(frozen=True)
class ZenohRoles:
    """Which zenoh users are workers and which are robots: the router's access control.

    Everything not allowed here is denied, so an authenticated client can only do its role's
    part: worker `W` (and its processes `W.anything`) asks on its own job keys and declares its
    own liveliness token; robot `R` declares `evocolony/robots/R/alive` and its agent's
    `evocolony/robots/R/agent/*` token and looks for other agents' there, subscribes to its own
    commands and its own tracker poses, publishes its own acks and asks on its own trace and
    replace keys; a tracker
    publishes robots' poses (`evocolony/tracker/*`) and nothing else. Only the server, inside
    the router, declares queryables and subscribers on others' keys.
    """

    workers: tuple[str, ...] = ()
    robots: tuple[str, ...] = ()
    trackers: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        names = [*self.workers, *self.robots, *self.trackers]
        for name in names:
            if not _NAME.match(name):
                raise ValueError(f"zenoh user {name!r} must match {_NAME.pattern}")
        for name in self.workers:
            if "." in name:  # else worker user "a" could take the names of worker user "a.b"
                raise ValueError(f"worker user {name!r} must not contain '.'")
        if len(set(names)) != len(names):
            raise ValueError("a zenoh user appears twice in the roles")

    @classmethod
    def from_file(cls, path: Path) -> ZenohRoles:
        """ValueError, naming the file, unless it is JSON {"workers": [...], "robots": [...]}."""
        try:
            data = json.loads(path.read_text())
            if not isinstance(data, dict) or set(data) - set(ROLES):
                raise ValueError('expected {"workers": [...], "robots": [...], "trackers": [...]}')
            lists = [data.get(role, []) for role in ROLES]
            if not all(isinstance(v, list) and all(isinstance(n, str) for n in v) for v in lists):
                raise ValueError("workers, robots and trackers must be lists of names")
            return cls(*(tuple(names) for names in lists))
        except (OSError, ValueError) as exc:
            raise ValueError(f"zenoh roles file {path}: {exc}") from exc

    def access_control(self) -> dict[str, object]:
        """zenoh's `access_control` config (default deny) granting each user its role."""
        rules: list[dict[str, object]] = []
        subjects: list[dict[str, object]] = []
        policies: list[dict[str, object]] = []
        for n, worker in enumerate(self.workers):
            own = [worker, f"{worker}.$*"]
            jobs = [f"evocolony/jobs/{kind}/{name}" for kind in ("next", "result") for name in own]
            ids = [f"w{n}-{part}" for part in ("ask", "reply", "alive", "see")]
            rules += [
                _allow(ids[0], ["query"], "ingress", jobs),
                _allow(ids[1], ["reply"], "egress", jobs),
                _allow(
                    ids[2], ["liveliness_token"], "ingress", [f"evocolony/workers/{o}" for o in own]
                ),
                _allow(ids[3], ["declare_queryable"], "egress", list(_SERVER_JOB_QUERYABLES)),
            ]
            subjects.append({"id": f"w{n}", "usernames": [worker]})
            policies.append({"id": f"w{n}", "rules": ids, "subjects": [f"w{n}"]})
        for n, robot in enumerate(self.robots):
            key = {kind: f"evocolony/robots/{robot}/{kind}" for kind in _ROBOT_KEYS}
            asks = [key["traces"], key["replace"]]
            agents = f"evocolony/robots/{robot}/agent/*"
            parts = ("alive", "sub", "cmd", "ack", "ask", "reply", "see", "where", "seen")
            ids = [f"r{n}-{part}" for part in (*parts, "look", "found")]
            rules += [
                _allow(ids[0], ["liveliness_token"], "ingress", [key["alive"], agents]),
                _allow(ids[1], ["declare_subscriber"], "ingress", [key["command"]]),
                _allow(ids[2], ["put"], "egress", [key["command"]]),
                _allow(ids[3], ["put"], "ingress", [key["ack"]]),
                _allow(ids[4], ["query"], "ingress", asks),
                _allow(ids[5], ["reply"], "egress", asks),
                _allow(ids[6], ["declare_queryable"], "egress", list(_SERVER_ROBOT_QUERYABLES)),
                _allow(ids[7], ["declare_subscriber"], "ingress", [f"evocolony/tracker/{robot}"]),
                _allow(ids[8], ["put"], "egress", [f"evocolony/tracker/{robot}"]),
                _allow(ids[9], ["liveliness_query"], "ingress", [agents]),
                _allow(ids[10], ["liveliness_token"], "egress", [agents]),
            ]
            subjects.append({"id": f"r{n}", "usernames": [robot]})
            policies.append({"id": f"r{n}", "rules": ids, "subjects": [f"r{n}"]})
        if self.trackers:
            rules.append(_allow("t-pose", ["put"], "ingress", ["evocolony/tracker/*"]))
            subjects.append({"id": "t", "usernames": list(self.trackers)})
            policies.append({"id": "t", "rules": ["t-pose"], "subjects": ["t"]})
        return {
            "enabled": True,
            "default_permission": "deny",
            "rules": rules,
            "subjects": subjects,
            "policies": policies,
        }


@dataclass(frozen=True)
class ZenohRouterAuth:
    """What the server's router adds: a user:password dictionary file, TLS certificate and key."""

    dictionary_file: Path | None = None
    """One `user:password` line per client; with it, clients without a valid pair are refused."""
    roles: ZenohRoles | None = None
    """What each user may do (required with `dictionary_file`: authentication without roles
    would let a robot's password act as a worker)."""
    certificate: Path | None = None
    private_key: Path | None = None
    root_ca: Path | None = None
    """For a router that itself connects to a lab zenohd over tls/."""
    user: str | None = None
    password: str | None = None
    """Credentials the router presents when it connects to a lab zenohd with usrpwd."""
    max_message_size: int = MAX_ZENOH_MESSAGE

    def __post_init__(self) -> None:
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("a TLS certificate and its private key go together")
        if (self.user is None) != (self.password is None):
            raise ValueError("zenoh user and password go together: give both or neither")
        if self.max_message_size < 1 << 16:
            raise ValueError(f"max_message_size must be >= 65536, got {self.max_message_size}")
        if (self.dictionary_file is None) != (self.roles is None):
            raise ValueError(
                "a zenoh users file and a roles file go together (colony lab init writes both)"
            )

    @property
    def authenticates(self) -> bool:
        """Whether clients must present a user:password pair of the lab."""
        return self.dictionary_file is not None

    def entries(self) -> list[tuple[str, str]]:
        """(key, json5 value) pairs for `zenoh.Config.insert_json5`."""
        out = [("transport/link/rx/max_message_size", str(self.max_message_size))]
        usrpwd: dict[str, str] = {}
        if self.dictionary_file is not None:
            usrpwd["dictionary_file"] = str(self.dictionary_file)
        if self.user is not None and self.password is not None:
            usrpwd.update(user=self.user, password=self.password)
        if usrpwd:
            out.append(("transport/auth/usrpwd", _json5(usrpwd)))
        if self.roles is not None:
            out.append(("access_control", _json5(self.roles.access_control())))
        tls: dict[str, str] = {}
        if self.certificate is not None and self.private_key is not None:
            tls.update(listen_certificate=str(self.certificate))
            tls.update(listen_private_key=str(self.private_key))
        if self.root_ca is not None:
            tls["root_ca_certificate"] = str(self.root_ca)
        if tls:
            out.append(("transport/link/tls", _json5(tls)))
        return out


# ------------------------------------------------------------------ signed controller pushes

SIGNING_CONTEXT = b"evocolony-signed-command-v1"


def signed_bytes(*, kind: str, robot: str, push_id: str, seq: int, document: str | None) -> bytes:
    """The exact bytes the server signs for one command to one robot.

    context, kind (push, stop, replacement), robot id, push id (for a replacement: the nonce of
    the stuck request it answers), sequence number and the sha256
    of the document's UTF-8 bytes (empty for a stop), newline-separated: a signature binds the
    document to this robot and this sequence number, so it cannot be replayed to another robot
    or, since agents keep the highest sequence seen, to the same robot later.
    """
    if seq < 0:
        raise ValueError(f"seq must be >= 0, got {seq}")
    digest = hashlib.sha256(document.encode()).hexdigest() if document is not None else ""
    fields = (kind, robot, push_id, str(seq), digest)
    if any("\n" in f for f in fields):
        raise ValueError("signed fields must not contain newlines")
    return SIGNING_CONTEXT + b"\n" + "\n".join(fields).encode()
