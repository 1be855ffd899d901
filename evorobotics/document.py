"""The controller document: the JSON the server stores, workers evaluate and robots run.

Format "evocolony.controller/1", canonical JSON (sorted keys, compact separators, UTF-8,
Python's shortest round-trip float repr), so one controller always gives byte-identical files:

    {"fitness": 12.5 | null,
     "format": "evocolony.controller/1",
     "provenance": {"run": "...", "generation": 349, ...},
     "validation": {<ValidationScore>},   (a run's champion only)
     "test": {<HeldOutScore>},               (a run's champion: its held-out figures)
     "world": {<World>},                  (when known: the world it was evolved in)
     "sha256": "<hex>",
     "spec": {<NetworkSpec, every field>},
     "weights": {"data": "<base64 of little-endian float64>", "dtype": "<f8", "shape": [n]}}

The id is `sha256` of canonical spec JSON + b"\\n" + the weights' little-endian float64 bytes.
The spec is hashed too, so two structurally different controllers (same weight count, other
layers) never share an id. Fitness, provenance, validation, test and world are not hashed: they
describe, not define.
Loading never unpickles; every malformed, non-finite or tampered document raises
`ControllerDocumentError` naming the problem.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from pydantic import ValidationError

from evorobotics.errors import ControllerDocumentError
from schemas.network import NetworkSpec
from schemas.run import HeldOutScore, ValidationScore
from schemas.world import World

FORMAT = "evocolony.controller/1"
"""The `format` field of every document this module writes and the only one it reads."""

Provenance = dict[str, str | int | float | None]

_FIELDS = frozenset({"format", "spec", "weights", "sha256", "fitness", "provenance"})
_OPTIONAL = frozenset({"validation", "world", "test"})
"""Members written only when known (a champion's); described, never hashed."""
_ANNOTATIONS = frozenset({"field"})
"""Members a server may add beside a document (field performance); read past, never hashed."""
_WEIGHT_FIELDS = frozenset({"dtype", "shape", "data"})


def _canonical(obj: object) -> str:
    return json.dumps(
        obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    )


def _spec_json(spec: NetworkSpec) -> str:
    return _canonical(spec.model_dump(mode="json"))


def controller_sha256(spec: NetworkSpec, weights: np.ndarray) -> str:
    """The controller's id: sha256 of canonical spec JSON, a newline, little-endian f8 weights."""
    w = np.asarray(weights, dtype="<f8")
    digest = hashlib.sha256(_spec_json(spec).encode("utf-8"))
    digest.update(b"\n")
    digest.update(w.tobytes())
    return digest.hexdigest()


@dataclass(frozen=True, eq=False)
class ControllerDocument:
    """One controller: spec, weights (read-only float64, 1-D), fitness and provenance."""

    spec: NetworkSpec
    weights: np.ndarray
    fitness: float | None = None
    provenance: Provenance = field(default_factory=dict)
    validation: ValidationScore | None = None
    """The champion's score on its run's validation set; None for any other controller."""
    world: World | None = None
    """The world it was evolved in (its run's `world`); None when unknown."""
    test: HeldOutScore | None = None
    """The champion's held-out test figures; None for any other controller."""

    def __post_init__(self) -> None:
        """Copy and check the arguments (ValueError), so a document is always trustworthy."""
        if not isinstance(self.spec, NetworkSpec):
            raise ValueError(f"spec must be a NetworkSpec, got {type(self.spec).__name__}")
        w = np.array(self.weights, dtype=np.float64)
        n = self.spec.weight_count
        if w.shape != (n,):
            raise ValueError(f"weights must have shape ({n},) for this spec, got {w.shape}")
        if not np.isfinite(w).all():
            bad = int(np.flatnonzero(~np.isfinite(w))[0])
            raise ValueError(f"weights must be finite; weight {bad} is {w[bad]}")
        w.flags.writeable = False
        object.__setattr__(self, "weights", w)
        if self.fitness is not None:
            if isinstance(self.fitness, bool) or not isinstance(self.fitness, int | float):
                raise ValueError(f"fitness must be a number or None, got {self.fitness!r}")
            if not math.isfinite(self.fitness):
                raise ValueError(f"fitness must be finite, got {self.fitness}")
            object.__setattr__(self, "fitness", float(self.fitness))
        object.__setattr__(self, "provenance", _checked_provenance(self.provenance))

    @cached_property
    def sha256(self) -> str:
        """Hex id of the controller (spec and weights; see the module docstring)."""
        return controller_sha256(self.spec, self.weights)

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready document (weights as base64 of little-endian float64)."""
        raw = self.weights.astype("<f8").tobytes()
        out: dict[str, Any] = {
            "format": FORMAT,
            "spec": self.spec.model_dump(mode="json"),
            "weights": {
                "dtype": "<f8",
                "shape": [int(self.weights.shape[0])],
                "data": base64.b64encode(raw).decode("ascii"),
            },
            "sha256": self.sha256,
            "fitness": self.fitness,
            "provenance": dict(self.provenance),
        }
        if self.validation is not None:
            out["validation"] = self.validation.model_dump(mode="json")
        if self.world is not None:
            out["world"] = self.world.model_dump(mode="json")
        if self.test is not None:
            out["test"] = self.test.model_dump(mode="json")
        return out

    def to_json(self) -> str:
        """Canonical JSON: the same controller always gives the same characters."""
        return _canonical(self.to_dict())

    @classmethod
    def from_dict(cls, obj: object) -> ControllerDocument:
        """Validate a parsed document; ControllerDocumentError naming what is wrong."""
        if not isinstance(obj, dict):
            raise ControllerDocumentError(
                f"a controller document is a JSON object, got {type(obj).__name__}"
            )
        if obj.get("format") != FORMAT:
            raise ControllerDocumentError(
                f"unknown format {obj.get('format')!r}; this reader understands {FORMAT!r}"
            )
        missing = sorted(_FIELDS - obj.keys())
        extra = sorted(set(obj) - _FIELDS - _OPTIONAL - _ANNOTATIONS)
        if missing or extra:
            raise ControllerDocumentError(f"missing fields {missing}, unknown fields {extra}")
        try:
            spec = NetworkSpec.model_validate(obj["spec"])
        except ValidationError as exc:
            raise ControllerDocumentError(f"invalid spec: {exc}") from None
        weights = _decode_weights(obj["weights"], spec)
        fitness = obj["fitness"]
        if fitness is not None and (
            isinstance(fitness, bool) or not isinstance(fitness, int | float)
        ):
            raise ControllerDocumentError(f"fitness must be a number or null, got {fitness!r}")
        if fitness is not None and not math.isfinite(fitness):
            raise ControllerDocumentError(f"non-finite fitness {fitness}")
        try:
            validation = (
                None
                if obj.get("validation") is None
                else ValidationScore.model_validate(obj["validation"])
            )
            world = None if obj.get("world") is None else World.model_validate(obj["world"])
            test = None if obj.get("test") is None else HeldOutScore.model_validate(obj["test"])
        except ValidationError as exc:
            raise ControllerDocumentError(f"invalid validation, test or world: {exc}") from None
        try:
            doc = cls(spec, weights, fitness, obj["provenance"], validation, world, test)
        except ValueError as exc:
            raise ControllerDocumentError(str(exc)) from None
        if obj["sha256"] != doc.sha256:
            raise ControllerDocumentError(
                f"sha256 mismatch: document says {obj['sha256']!r}, content hashes to "
                f"{doc.sha256!r} (corrupted or tampered)"
            )
        return doc

    @classmethod
    def from_json(cls, text: str | bytes) -> ControllerDocument:
        """Parse and validate a document (never unpickles anything)."""
        try:
            obj = json.loads(text)
        except (UnicodeDecodeError, ValueError) as exc:
            raise ControllerDocumentError(f"invalid JSON: {exc}") from None
        return cls.from_dict(obj)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ControllerDocument):
            return NotImplemented
        return self.to_json() == other.to_json()

    def __hash__(self) -> int:
        return hash(self.to_json())


def _checked_provenance(provenance: object) -> Provenance:
    """A copy of `provenance`, or ValueError: string keys, JSON scalar values, finite floats."""
    if not isinstance(provenance, dict):
        raise ValueError(f"provenance must be an object, got {type(provenance).__name__}")
    out: Provenance = {}
    for key, value in provenance.items():
        if not isinstance(key, str):
            raise ValueError(f"provenance keys must be strings, got {key!r}")
        if value is not None and not isinstance(value, str | int | float):
            raise ValueError(
                f"provenance {key!r} must be a string, number or null, got {type(value).__name__}"
            )
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"provenance {key!r} must be finite, got {value}")
        out[key] = value
    return out


def _decode_weights(obj: object, spec: NetworkSpec) -> np.ndarray:
    """The weights of a document's "weights" object, checked against `spec`."""
    if not isinstance(obj, dict) or set(obj) != _WEIGHT_FIELDS:
        raise ControllerDocumentError(
            f"weights must be an object with fields {sorted(_WEIGHT_FIELDS)}"
        )
    if obj["dtype"] != "<f8":
        raise ControllerDocumentError(f"weights dtype must be '<f8', got {obj['dtype']!r}")
    n = spec.weight_count
    if obj["shape"] != [n]:
        raise ControllerDocumentError(
            f"weights shape {obj['shape']!r} does not match the spec's {n} weights"
        )
    data = obj["data"]
    if not isinstance(data, str):
        raise ControllerDocumentError("weights data must be a base64 string")
    try:
        raw = base64.b64decode(data, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise ControllerDocumentError(f"weights data is not valid base64: {exc}") from None
    if len(raw) != 8 * n:
        raise ControllerDocumentError(
            f"weights data holds {len(raw)} bytes; shape [{n}] of '<f8' needs {8 * n}"
        )
    w = np.frombuffer(raw, dtype="<f8").astype(np.float64)
    if not np.isfinite(w).all():
        bad = int(np.flatnonzero(~np.isfinite(w))[0])
        raise ControllerDocumentError(f"weights must be finite (NaN/inf): weight {bad} is {w[bad]}")
    return w
