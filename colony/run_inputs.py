"""Run inputs given on the command line as files: a maze file or a NetworkSpec JSON file.

`colony evolve` and `colony run start` read them here, so a run's config carries the contents
(maze text, a NetworkSpec) and reproduces anywhere without the file. Light: no simulator.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError

from schemas.network import PRESETS, NetworkSpec

TEXT_MAZE = "maze '<text>'"
"""How `evorobotics.maze` names a maze given as text, which is how a maze file travels."""


class ConfigError(Exception):
    """A flag, config file, maze or network is invalid; the message is one line for the user."""


def validation_message(err: ValidationError, prefix: str = "") -> str:
    """'field: reason; ...' from pydantic's errors, naming every offending field."""
    parts = []
    for e in err.errors():
        loc = ".".join(str(x) for x in (prefix, *e["loc"]) if x != "")
        msg = str(e["msg"]).removeprefix("Value error, ")
        parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)


def network_value(value: str) -> str | NetworkSpec:
    """A preset name stays a name; an existing file is read as a NetworkSpec JSON."""
    if value in PRESETS:
        return value
    path = Path(value)
    if path.is_file():
        try:
            return NetworkSpec.model_validate_json(path.read_bytes())
        except ValidationError as err:
            raise ConfigError(f"network file {value}: {validation_message(err)}") from None
        except OSError as err:
            raise ConfigError(f"network file {value}: cannot read it: {err.strerror}") from None
    raise ConfigError(
        f"network: {value!r} is neither a preset {sorted(PRESETS)} nor a NetworkSpec JSON file"
    )


def maze_value(value: str) -> str:
    """An existing file becomes its text (remote workers need no file); a name stays a name."""
    path = Path(value)
    if not path.is_file():
        return value
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ConfigError(
            f"maze file {value}: not a text maze file (binary or not UTF-8)"
        ) from None
    except OSError as err:
        raise ConfigError(f"maze file {value}: cannot read it: {err.strerror}") from None


def name_maze_file(message: str, maze: str | None) -> str:
    """`message` about the maze text read from file `maze` (the `--maze` value) naming that
    file, as the user knows it, instead of the text."""
    if maze is None or not Path(maze).is_file():
        return message
    return message.replace(TEXT_MAZE, f"maze file {maze}")
