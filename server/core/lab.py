"""A lab's credentials in one directory: `colony lab init` (docs/deployment.md).

One zenoh user per worker host and per robot, each with its own password, and a roles file
that the server's router turns into access control (schemas.security.ZenohRoles); the REST
token; the server's signing key with its public half for robots to pin; and, for TLS, a CA and
the router's certificate. Every secret file is mode 600. Each process gets an env file of
`COLONY_*` settings, so starting it is `env $(cat F) colony ...` or compose's `env_file`.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import secrets
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from schemas.security import ZenohRoles
from server.core.keys import load_or_create_key, public_pem

LOCAL_WORKERS = "local"
"""The zenoh user of the server's own local workers (`colony server --workers N`)."""
CERT_DAYS = 3650


@dataclass(frozen=True)
class Lab:
    """What `init_lab` wrote: the env file of each process, by role and name."""

    root: Path
    server_env: Path
    worker_envs: dict[str, Path]
    robot_envs: dict[str, Path]
    tracker_envs: dict[str, Path]


def _write(path: Path, text: str, *, secret: bool) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600 if secret else 0o644)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def _env(values: dict[str, str]) -> str:
    for key, value in values.items():
        if any(c in value for c in "\n'$ "):
            raise ValueError(f"{key}: {value!r} cannot go into an env file unquoted")
    return "".join(f"{key}={value}\n" for key, value in values.items())


def _pem(obj: x509.Certificate) -> str:
    return obj.public_bytes(serialization.Encoding.PEM).decode()


def _key_pem(key: ec.EllipticCurvePrivateKey) -> str:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    ).decode()


def certificates(hosts: Sequence[str], now: datetime.datetime) -> tuple[str, str, str]:
    """PEMs of a new CA, and a router certificate and key it signed, valid for `hosts` (DNS
    names or IP addresses, as clients will connect to them). The CA's key is dropped: nothing
    needs it once the one certificate is signed, and a kept key could mint others."""
    if not hosts:
        raise ValueError("a TLS certificate needs at least one host name or address")
    later = now + datetime.timedelta(days=CERT_DAYS)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "EvoColony lab CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now)
        .not_valid_after(later)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, hosts[0])]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now)
        .not_valid_after(later)
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    return _pem(ca), _pem(cert), _key_pem(key)


def init_lab(
    root: Path,
    *,
    workers: Sequence[str],
    robots: Sequence[str],
    server_host: str,
    trackers: Sequence[str] = ("tracker",),
    tls: bool = False,
    port: int = 7447,
    paths_as: Path | None = None,
    now: datetime.datetime | None = None,
) -> Lab:
    """Write a lab's credentials under `root`, which must not exist or be empty.

    `server_host`: the name or address workers and robots reach the server at (and the TLS
    certificate's name). The server listens on all interfaces at `port` (tls/ with `tls`),
    and its local workers on tcp loopback. `paths_as`: where `root` will be seen by the
    processes (a container's mount point), used in the env files instead of `root`.
    ValueError for a bad name or a non-empty `root`.
    """
    roles = ZenohRoles(
        workers=(LOCAL_WORKERS, *workers), robots=tuple(robots), trackers=tuple(trackers)
    )
    if root.exists() and any(root.iterdir()):
        raise ValueError(f"{root} is not empty: lab credentials are written once")
    root.mkdir(parents=True, exist_ok=True)
    seen = (paths_as or root.resolve()).as_posix()
    users = (*roles.workers, *roles.robots, *roles.trackers)
    passwords = {user: secrets.token_urlsafe(24) for user in users}
    _write(root / "zenoh-users", "".join(f"{u}:{p}\n" for u, p in passwords.items()), secret=True)
    roles_json = {
        "workers": list(roles.workers),
        "robots": list(roles.robots),
        "trackers": list(roles.trackers),
    }
    _write(root / "zenoh-roles.json", json.dumps(roles_json, indent=2) + "\n", secret=False)
    key = load_or_create_key(root / "server-key.pem")
    _write(root / "server-key.pub.pem", public_pem(key), secret=False)

    scheme = "tls" if tls else "tcp"
    listen = [f"{scheme}/0.0.0.0:{port}"] + ([f"tcp/127.0.0.1:{port - 1}"] if tls else [])
    server = {
        "COLONY_HOST": "0.0.0.0",
        "COLONY_ZENOH_LISTEN": json.dumps(listen, separators=(",", ":")),
        "COLONY_API_TOKEN": secrets.token_urlsafe(32),
        "COLONY_SERVER_KEY": f"{seen}/server-key.pem",
        "COLONY_ZENOH_USERS_FILE": f"{seen}/zenoh-users",
        "COLONY_ZENOH_ROLES_FILE": f"{seen}/zenoh-roles.json",
        "COLONY_ZENOH_USER": LOCAL_WORKERS,
        "COLONY_ZENOH_PASSWORD": passwords[LOCAL_WORKERS],
    }
    client = {"COLONY_CONNECT": f"{scheme}/{server_host}:{port}"}
    if tls:
        hosts = list(dict.fromkeys([server_host, "localhost", "127.0.0.1"]))
        ca, cert, cert_key = certificates(hosts, now or datetime.datetime.now(datetime.UTC))
        _write(root / "ca.pem", ca, secret=False)
        _write(root / "zenoh-cert.pem", cert, secret=False)
        _write(root / "zenoh-key.pem", cert_key, secret=True)
        server["COLONY_ZENOH_TLS_CERTIFICATE"] = f"{seen}/zenoh-cert.pem"
        server["COLONY_ZENOH_TLS_PRIVATE_KEY"] = f"{seen}/zenoh-key.pem"
        client["COLONY_ZENOH_ROOT_CA"] = f"{seen}/ca.pem"
    _write(root / "server.env", _env(server), secret=True)

    def user_env(user: str, extra: dict[str, str]) -> str:
        return _env(
            {"COLONY_ZENOH_USER": user, "COLONY_ZENOH_PASSWORD": passwords[user], **client, **extra}
        )

    worker_envs = {w: root / "workers" / f"{w}.env" for w in workers}
    for name, path in worker_envs.items():
        _write(path, user_env(name, {}), secret=True)
    robot_envs = {r: root / "robots" / f"{r}.env" for r in robots}
    for name, path in robot_envs.items():
        pinned = {"COLONY_ROBOT_ID": name, "COLONY_SERVER_PUBLIC_KEY": f"{seen}/server-key.pub.pem"}
        _write(path, user_env(name, pinned), secret=True)
    tracker_envs = {t: root / "trackers" / f"{t}.env" for t in trackers}
    for name, path in tracker_envs.items():  # its own names: it runs beside a robot's agent
        tracker = {"COLONY_TRACKER_USER": name, "COLONY_TRACKER_PASSWORD": passwords[name]}
        _write(path, _env({**tracker, **client}), secret=True)
    return Lab(root, root / "server.env", worker_envs, robot_envs, tracker_envs)
