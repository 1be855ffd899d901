"""A lab in network namespaces (docs/operations.md): five hosts on a bridge with private
addresses, real `colony` processes with a lab's credentials from `colony lab init --tls`, and an
intruder on the same network.

Each host is a network namespace with a veth into a bridge in the root namespace (which has an
address on the lab network too, as the operator's machine). The server, two workers and a
virtual robot authenticate with their own credentials over TLS: a run completes, both workers
take jobs, the robot takes a signed push. From the fifth host, a client without credentials
cannot connect at all, and one with a robot's credentials can act neither as a worker nor as
another robot (the router drops its queries: no reply of any kind), while a query on its own
robot's key gets the server's answer.
"""

from __future__ import annotations

import ipaddress
import json
import os
import secrets
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from tests.helpers import eventually, online, wait_status

pytestmark = pytest.mark.slow

HOSTS = ("server", "worker1", "worker2", "robot", "intruder")
WORKERS = ("worker-1", "worker-2")
ROBOT, STOLEN = "evbot-1", "evbot-2"
"""The robot that runs, and the robot whose credentials the intruder holds."""
RUN = {"population": 16, "generations": 3, "trials": 1, "steps": 40, "seed": 7, "job_size": 2}
WAIT = 45.0
BIN = Path(sys.executable).parent
SETUP_TIMEOUT_S = 10.0

PROBE = """
import json, sys
from pathlib import Path
import zenoh
from schemas.robots import traces_key
from schemas.security import ZenohClientAuth
from schemas.wire import JobRequest, encode, next_key
from worker.main import WorkerSettings

connect, ca, user, password, own, other = sys.argv[1:7]

def session(auth):
    settings = WorkerSettings(connect=(connect,), name=auth.user or "probe", auth=auth)
    return zenoh.open(settings.zenoh_config())

def refused(auth):
    try:
        session(auth).close()
    except zenoh.ZError:
        return True
    return False

def replies(s, key, payload):
    return len(list(s.get(key, payload=payload, timeout=2.0)))

out = {
    "anonymous_refused": refused(ZenohClientAuth(root_ca=Path(ca))),
    "wrong_password_refused": refused(ZenohClientAuth(user, "not-" + password, Path(ca))),
}
with session(ZenohClientAuth(user, password, Path(ca))) as s:
    out["as_worker"] = replies(s, next_key(own), encode(JobRequest(worker=own)))
    out["as_other_robot"] = replies(s, traces_key(other), b"")
    out["as_itself"] = replies(s, traces_key(own), b"")
print(json.dumps(out))
"""
"""Run by the intruder host: prints how many replies each query got, and whether the router
refused a session without credentials or with a wrong password."""


def _ip(*argv: str) -> None:
    done = subprocess.run(
        ["ip", *argv], capture_output=True, text=True, timeout=SETUP_TIMEOUT_S, check=False
    )
    if done.returncode != 0:
        raise OSError(f"ip {' '.join(argv)}: {done.stderr.strip()}")


def _free_subnet() -> ipaddress.IPv4Network:
    """A 10.231.X.0/24 no interface of the root namespace uses yet."""
    used = subprocess.run(["ip", "-4", "route"], capture_output=True, text=True, check=False).stdout
    for x in secrets.SystemRandom().sample(range(1, 255), 254):
        net = ipaddress.IPv4Network(f"10.231.{x}.0/24")
        if str(net.network_address)[:-1] not in used:
            return net
    raise OSError("no free 10.231.X.0/24 subnet")


@dataclass(frozen=True)
class Network:
    """Namespace and address of each host."""

    namespaces: dict[str, str]
    addresses: dict[str, str]


@pytest.fixture
def network() -> Iterator[Network]:
    """Five namespaces on a bridge; skipped, with the reason, where they cannot be made.
    Everything made is removed afterwards, also on failure (a namespace's veth end takes its
    peer with it)."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2)")
    tag = secrets.token_hex(3)
    bridge = f"evcbr{tag}"
    namespaces = {host: f"evc-{tag}-{host}" for host in HOSTS}
    made: list[str] = []
    try:
        try:
            _ip("netns", "add", namespaces["server"])
        except OSError as exc:
            pytest.skip(f"`ip netns add` fails here: {exc}")
        made.append(namespaces["server"])
        try:
            for host in HOSTS[1:]:
                _ip("netns", "add", namespaces[host])
                made.append(namespaces[host])
            net = _free_subnet()
            hosts = list(net.hosts())
            _ip("link", "add", bridge, "type", "bridge")
            # the root namespace on the lab network: the operator's machine
            _ip("addr", "add", f"{hosts[0]}/{net.prefixlen}", "dev", bridge)
            _ip("link", "set", bridge, "up")
            addresses = {}
            for k, host in enumerate(HOSTS):
                ns, outer, address = namespaces[host], f"evc{tag}v{k}", str(hosts[10 + k])
                _ip("link", "add", outer, "type", "veth", "peer", "name", "eth0", "netns", ns)
                _ip("link", "set", outer, "master", bridge, "up")
                _ip("-n", ns, "addr", "add", f"{address}/{net.prefixlen}", "dev", "eth0")
                _ip("-n", ns, "link", "set", "eth0", "up")
                _ip("-n", ns, "link", "set", "lo", "up")
                addresses[host] = address
        except OSError as exc:
            pytest.skip(f"namespaces, but no bridge and veth network here: {exc}")
        yield Network(namespaces, addresses)
    finally:
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)
        subprocess.run(["ip", "link", "del", bridge], capture_output=True, check=False)


def read_env(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line)


class Hosts:
    """Processes started in the namespaces, each with only its own env file's COLONY_*
    settings; all killed at the end."""

    def __init__(self, network: Network, logs: Path) -> None:
        self.network = network
        self.logs = logs
        self.procs: list[subprocess.Popen[bytes]] = []
        self.base = {k: v for k, v in os.environ.items() if not k.startswith("COLONY_")}

    def start(self, host: str, env: dict[str, str], *argv: str) -> subprocess.Popen[bytes]:
        with (self.logs / f"{host}.log").open("ab") as log:
            proc = subprocess.Popen(
                ["ip", "netns", "exec", self.network.namespaces[host], str(BIN / "colony"), *argv],
                env={**self.base, **env},
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        self.procs.append(proc)
        return proc

    def run(self, host: str, env: dict[str, str], *argv: str) -> str:
        argv_ns = ["ip", "netns", "exec", self.network.namespaces[host], *argv]
        done = subprocess.run(argv_ns, env={**self.base, **env}, capture_output=True, timeout=WAIT)
        assert done.returncode == 0, done.stderr.decode()
        return done.stdout.decode()

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)

    def log(self) -> str:
        return "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in self.logs.glob("*.log"))


def test_a_lab_on_a_bridge_runs_authenticated_and_keeps_an_intruder_out(
    network: Network, tmp_path: Path
) -> None:
    server_ip = network.addresses["server"]
    lab = tmp_path / "lab"
    init = ["lab", "init", str(lab), "--server-host", server_ip, "--tls"]
    for name in WORKERS:
        init += ["--worker", name]
    for name in (ROBOT, STOLEN):
        init += ["--robot", name]
    made = subprocess.run([str(BIN / "colony"), *init], capture_output=True, timeout=WAIT)
    assert made.returncode == 0, made.stderr.decode()
    server_env = read_env(lab / "server.env")
    token = server_env["COLONY_API_TOKEN"]
    logs = tmp_path / "logs"
    logs.mkdir()
    hosts = Hosts(network, logs)
    url = f"http://{server_ip}:8000"
    http = httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=10)
    try:
        server = hosts.start(
            "server",
            server_env,
            *("server", "--db", f"sqlite:///{tmp_path / 'colony.db'}", "--workers", "0"),
        )

        def healthy() -> bool:
            assert server.poll() is None, hosts.log()
            try:
                return http.get("/healthz", timeout=1).is_success
            except httpx.TransportError:
                return False

        assert eventually(healthy, timeout=WAIT), hosts.log()
        for k, name in enumerate(WORKERS, 1):
            hosts.start(f"worker{k}", read_env(lab / "workers" / f"{name}.env"), "worker")
        robot_env = read_env(lab / "robots" / f"{ROBOT}.env")
        hosts.start("robot", robot_env, "agent", "--emulate", "--state-dir", str(tmp_path / ROBOT))

        def joined() -> set[str]:
            return {w["name"].split(".")[0] for w in http.get("/api/workers").json()}

        assert eventually(lambda: joined() == set(WORKERS), timeout=WAIT), hosts.log()
        assert httpx.post(f"{url}/api/runs", json=RUN).status_code == 401
        run_id = http.post("/api/runs", json=RUN).json()["id"]
        done = wait_status(http, run_id, {"completed", "failed"})
        assert done["status"] == "completed", done
        jobs = {w["name"].split(".")[0]: w["jobs_done"] for w in http.get("/api/workers").json()}
        assert all(jobs.get(name, 0) > 0 for name in WORKERS), jobs

        assert eventually(lambda: online(http, ROBOT), timeout=WAIT), hosts.log()
        pushed = http.post(f"/api/robots/{ROBOT}/controller", json={"run_id": run_id})
        assert pushed.status_code == 200 and pushed.json()["accepted"], pushed.text

        stolen = read_env(lab / "robots" / f"{STOLEN}.env")
        probe = hosts.run(
            "intruder",
            {},
            sys.executable,
            "-c",
            PROBE,
            stolen["COLONY_CONNECT"],
            stolen["COLONY_ZENOH_ROOT_CA"],
            stolen["COLONY_ZENOH_USER"],
            stolen["COLONY_ZENOH_PASSWORD"],
            STOLEN,
            ROBOT,
        )
        assert json.loads(probe) == {
            "anonymous_refused": True,
            "wrong_password_refused": True,
            "as_worker": 0,
            "as_other_robot": 0,
            "as_itself": 1,
        }, hosts.log()
    finally:
        http.close()
        hosts.close()
