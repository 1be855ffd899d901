"""docker-compose.yml: structurally sound, and every `colony` command in it exists in the CLI.

No Docker engine runs here and PyYAML is not a dependency, so this parses the small YAML
subset the file uses (block maps, `- item` lists, JSON-style flow lists and scalars).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

from colony.cli import app

COMPOSE = Path(__file__).resolve().parents[1] / "docker-compose.yml"


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


def test_compose_parses_with_the_expected_services() -> None:
    doc = parse_subset(COMPOSE.read_text())
    services = doc["services"]
    assert {"zenoh", "server", "worker"} <= set(services)
    assert services["zenoh"]["image"].startswith("eclipse/zenoh")
    assert "tcp/0.0.0.0:7447" in services["zenoh"]["command"]
    assert "colony-data" in doc["volumes"]
    for name, service in services.items():
        assert isinstance(service["command"], list), name
        assert all(isinstance(word, str) for word in service["command"]), name


def test_every_colony_command_in_compose_exists() -> None:
    services = parse_subset(COMPOSE.read_text())["services"]
    commands = [s["command"] for s in services.values() if s["command"][0] == "colony"]
    assert len(commands) >= 2
    for argv in commands:
        command, options = colony_options(argv[1:])
        used = {word for word in argv[1:] if word.startswith("--")}
        assert used <= options, f"colony {command} lacks {sorted(used - options)}"
        endpoints = [w for w in argv if w.startswith("tcp/")]
        assert endpoints == ["tcp/zenoh:7447"], argv


def test_subset_parser_rejects_broken_structure() -> None:
    for broken in ("a:\n   b: 1\n", "a:\n\t- x\n", "- x\n", "a:\n  b: [1,\n"):
        try:
            parse_subset(broken)
        except ValueError:
            continue
        raise AssertionError(f"accepted {broken!r}")
