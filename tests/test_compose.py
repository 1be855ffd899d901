"""docker-compose.yml: secure defaults, every `colony` command in it exists, and the lab that
docs/deployment.md makes gives each service the credentials and files it needs.

No Docker engine runs here and PyYAML is not a dependency, so this parses the small YAML
subset the file uses (block maps, `- item` lists, JSON-style flow lists and scalars) and
resolves what compose would: env files, `${VAR:?msg}` / `${VAR:-default}` from `.env`, bind
mounts. The server's resolved environment then goes through the server's own settings and
start-up checks (token, zenoh authentication and roles).
"""

from __future__ import annotations

import json
import os
import re
import shlex
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from colony.cli import app
from schemas.security import ZenohRoles
from server.core.auth import check_bind
from server.core.keys import load_or_create_key, public_pem
from server.core.settings import Settings
from server.runs.dispatch import DispatchSettings

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
COMPOSE_TLS = ROOT / "docker-compose.tls.yml"
DEPLOYMENT = ROOT / "docs" / "deployment.md"
LAB_INIT = "colony lab init lab --server-host server --paths-as /lab --workers 1 --robots 2"
"""The command docker-compose.yml's header and docs/deployment.md give."""
PASSWORD = "0123456789abcdef0123456789abcdef"
DOTENV = {"POSTGRES_PASSWORD": PASSWORD, "COLONY_UID": "1000", "COLONY_GID": "1000"}
"""What the documented `.env` holds (its password is hex, as the documented command makes)."""


def parse_subset(text: str) -> dict[str, Any]:
    """Block mappings and sequences by two-space indentation; values are JSON or bare words."""
    root: dict[str, Any] = {}
    stack: list[tuple[int, Any]] = [(-1, root)]
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split(" #", 1)[0].rstrip() if not raw.lstrip().startswith("#") else ""
        if not line:
            continue
        if "\t" in raw:
            raise ValueError(f"line {number}: tab")
        indent = len(line) - len(line.lstrip())
        if indent % 2:
            raise ValueError(f"line {number}: odd indentation")
        body = line.strip()
        while stack[-1][0] >= indent:
            stack.pop()
        parent = stack[-1][1]
        if body.startswith("- "):
            if not isinstance(parent, list):
                raise ValueError(f"line {number}: list item outside a list")
            parent.append(_scalar(body[2:], number))
            continue
        key, sep, rest = body.partition(":")
        if not sep or not key or not isinstance(parent, dict):
            raise ValueError(f"line {number}: expected 'key: value'")
        if rest.strip():
            parent[key] = _scalar(rest.strip(), number)
        else:
            parent[key] = _container(text.splitlines()[number:], indent)
            stack.append((indent, parent[key]))
    return root


def _container(following: list[str], indent: int) -> Any:
    for raw in following:
        if raw.strip() and not raw.lstrip().startswith("#"):
            deeper = len(raw) - len(raw.lstrip()) > indent
            return [] if deeper and raw.strip().startswith("- ") else {}
    return {}


def _scalar(text: str, number: int) -> Any:
    if text[0] in '[{"':
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"line {number}: {exc}") from exc
    return text


def colony_options(words: list[str]) -> tuple[str, set[str]]:
    """The name of the command a `colony ...` argv selects, and the option names it accepts."""
    command: Any = typer.main.get_command(app)
    for word in words:
        if word.startswith("-") or not isinstance(command, typer.core.TyperGroup):
            break
        sub = command.commands.get(word)
        assert sub is not None, f"`colony {word}` does not exist"
        command = sub
    names = {opt for p in command.params for opt in getattr(p, "opts", [])}
    return str(command.name), names


def services(*files: Path) -> dict[str, dict[str, Any]]:
    """The services of compose files merged as `docker compose -f A -f B` does for the keys
    these files use: later scalars win, `volumes` lists are appended."""
    merged: dict[str, dict[str, Any]] = {}
    for path in files:
        for name, service in parse_subset(path.read_text())["services"].items():
            into = merged.setdefault(name, {})
            for key, value in service.items():
                into[key] = into.get(key, []) + value if key == "volumes" else value
    return merged


def interpolate(text: str, dotenv: dict[str, str]) -> str:
    """Compose's `${VAR:?message}` and `${VAR:-default}` with variables from `.env`."""

    def one(match: re.Match[str]) -> str:
        name, op, arg = match.group(1), match.group(2), match.group(3)
        if dotenv.get(name):
            return dotenv[name]
        assert op == ":-", f"${{{name}}} is unset: {arg}"
        return arg

    return re.sub(r"\$\{(\w+)(:\?|:-)([^}]*)\}", one, text)


def read_env(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line)


def environment(service: dict[str, Any], project: Path) -> dict[str, str]:
    """What the container sees: its env files in order, then `environment`."""
    env: dict[str, str] = {}
    for name in service.get("env_file", []):
        assert (project / name).is_file(), f"env_file {name} is not written by the lab"
        env |= read_env(project / name)
    env |= {k: interpolate(v, DOTENV) for k, v in service.get("environment", {}).items()}
    return env


def mounts(service: dict[str, Any], project: Path) -> dict[str, tuple[Path, bool]]:
    """Bind mounts: container path -> (host path, read-only)."""
    found = {}
    for volume in service.get("volumes", []):
        source, target, *mode = volume.split(":")
        if source.startswith("./"):
            found[target] = (project / source, mode == ["ro"])
    return found


def on_host(path: str, binds: dict[str, tuple[Path, bool]]) -> tuple[Path, bool]:
    """The host file a container path is, through the service's bind mounts."""
    for target, (source, read_only) in binds.items():
        if path == target or path.startswith(target + "/"):
            host = source / path[len(target) :].lstrip("/") if path != target else source
            assert host.exists(), f"{path} is mounted from {host}, which the lab did not write"
            return host, read_only
    raise AssertionError(f"{path} is not mounted into the service")


def make_lab(project: Path, *extra: str) -> None:
    """The documented `colony lab init`, run in `project` (beside the compose file)."""
    words = shlex.split(LAB_INIT)[1:]
    words[words.index("lab", 2)] = str(project / "lab")
    result = CliRunner().invoke(app, [*words, *extra])
    assert result.exit_code == 0, result.output


def colony_services(found: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    return {name: s for name, s in found.items() if s["command"][0] == "colony"}


def test_compose_parses_with_the_expected_services() -> None:
    doc = parse_subset(COMPOSE.read_text())
    found = doc["services"]
    assert set(found) == {"server", "postgres", "worker", "evbot-1", "evbot-2"}
    assert not any(s.get("image", "").startswith("eclipse/zenoh") for s in found.values())
    assert {"colony-pg", "robot-state"} <= set(doc["volumes"])
    for name, service in found.items():
        assert isinstance(service["command"], list), name
        assert all(isinstance(word, str) for word in service["command"]), name
    published = {name: s["ports"] for name, s in found.items() if "ports" in s}
    assert published == {"server": ["8000:8000"]}, "only HTTP is published"


def test_every_colony_command_in_compose_exists() -> None:
    commands = [s["command"] for s in colony_services(services(COMPOSE)).values()]
    assert len(commands) == 4
    for argv in commands:
        command, options = colony_options(argv[1:])
        used = {word for word in argv[1:] if word.startswith("--")}
        assert used <= options, f"colony {command} lacks {sorted(used - options)}"
        assert not [w for w in argv if "/" in w and w.split("/")[0] in ("tcp", "tls")], (
            "zenoh endpoints come from the lab's env files"
        )


def test_no_insecure_flag_and_no_literal_secret() -> None:
    for path in (COMPOSE, COMPOSE_TLS):
        assert "--insecure-no-verify" not in path.read_text(), path.name
    found = services(COMPOSE)
    assert found["postgres"]["environment"]["POSTGRES_PASSWORD"].startswith("${POSTGRES_PASSWORD:?")
    assert "${POSTGRES_PASSWORD:?" in found["server"]["environment"]["COLONY_DB_URL"]
    for name, service in found.items():
        for key in service.get("environment", {}):
            assert not re.search("TOKEN|ZENOH_PASSWORD|ZENOH_USER", key), f"{name}: {key}"
    robots = [s for s in colony_services(found).values() if "agent" in s["command"]]
    assert robots and all("--emulate" in s["command"] for s in robots)


def test_lab_and_dotenv_stay_out_of_git_and_the_image() -> None:
    for name, lab in ((".gitignore", "/lab/"), (".dockerignore", "lab/")):
        lines = (ROOT / name).read_text().splitlines()
        assert lab in lines and any(line in (".env", "/.env") for line in lines), name


def test_the_documented_commands_are_in_the_docs() -> None:
    docs = DEPLOYMENT.read_text()
    assert LAB_INIT in COMPOSE.read_text() and LAB_INIT in docs
    assert "docker compose -f docker-compose.yml -f docker-compose.tls.yml up" in docs


def test_the_documented_lab_gives_every_service_its_credentials(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    make_lab(tmp_path)
    found = services(COMPOSE)
    users = dict(
        line.split(":", 1) for line in (tmp_path / "lab" / "zenoh-users").read_text().splitlines()
    )
    roles = ZenohRoles.from_file(tmp_path / "lab" / "zenoh-roles.json")

    server = found["server"]
    env, binds = environment(server, tmp_path), mounts(server, tmp_path)
    assert env["COLONY_API_TOKEN"] and env["COLONY_HOST"] == "0.0.0.0"
    assert env["COLONY_DB_URL"] == f"postgresql+psycopg://colony:{PASSWORD}@postgres:5432/colony"
    assert interpolate(found["postgres"]["environment"]["POSTGRES_PASSWORD"], DOTENV) == PASSWORD
    key, key_read_only = on_host(env["COLONY_SERVER_KEY"], binds)
    assert not key_read_only, "the signing sequence is written beside the key"
    for name in [k for k in os.environ if k.startswith("COLONY_")]:
        monkeypatch.delenv(name)
    for name, value in env.items():
        path = on_host(value, binds)[0] if value.startswith("/lab/") else value
        monkeypatch.setenv(name, str(path))
    settings = Settings()
    check_bind(settings.host, settings.api_token)
    dispatch = DispatchSettings.from_settings(settings)
    assert dispatch.listen == ("tcp/0.0.0.0:7447",) and not dispatch.connect
    assert dispatch.auth.authenticates and dispatch.auth.roles == roles

    for name, service in colony_services(found).items():
        if name == "server":
            continue
        env, binds = environment(service, tmp_path), mounts(service, tmp_path)
        assert env["COLONY_CONNECT"] == "tcp/server:7447", name
        user = env["COLONY_ZENOH_USER"]
        assert users[user] == env["COLONY_ZENOH_PASSWORD"], name
        assert all(read_only for _, read_only in binds.values()), name
        assert not any(target in ("/lab", "/lab/") for target in binds), "only public files"
        if service["command"][1] == "worker":
            assert user in roles.workers and name == "worker"
            continue
        assert user == env["COLONY_ROBOT_ID"] == name and user in roles.robots
        pinned, _ = on_host(env["COLONY_SERVER_PUBLIC_KEY"], binds)
        assert pinned.read_text() == public_pem(load_or_create_key(key))
    poses = [s["command"] for s in found.values() if "--index" in s["command"]]
    assert len({argv[argv.index("--index") + 1] for argv in poses}) == 2, "a pose per robot"


def test_the_tls_override_mounts_the_ca_for_every_client(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    make_lab(tmp_path, "--tls")
    found = services(COMPOSE, COMPOSE_TLS)
    server = found["server"]
    env, binds = environment(server, tmp_path), mounts(server, tmp_path)
    for name in ("COLONY_ZENOH_TLS_CERTIFICATE", "COLONY_ZENOH_TLS_PRIVATE_KEY"):
        on_host(env[name], binds)
    assert json.loads(env["COLONY_ZENOH_LISTEN"])[0] == "tls/0.0.0.0:7447"
    for name, service in colony_services(found).items():
        if name == "server":
            continue
        env, binds = environment(service, tmp_path), mounts(service, tmp_path)
        assert env["COLONY_CONNECT"] == "tls/server:7447", name
        ca, read_only = on_host(env["COLONY_ZENOH_ROOT_CA"], binds)
        assert read_only and ca == tmp_path / "lab" / "ca.pem", name


def test_subset_parser_rejects_broken_structure() -> None:
    for broken in ("a:\n   b: 1\n", "a:\n\t- x\n", "- x\n", "a:\n  b: [1,\n"):
        try:
            parse_subset(broken)
        except ValueError:
            continue
        raise AssertionError(f"accepted {broken!r}")
