"""The controller document: canonical JSON, content hash, and every way a document is refused."""

from __future__ import annotations

import base64
import hashlib
import json
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.document import FORMAT, ControllerDocument, controller_sha256
from evorobotics.errors import ControllerDocumentError
from schemas.network import PRESETS, NetworkSpec


@st.composite
def documents(draw: st.DrawFn) -> ControllerDocument:
    hidden = tuple(draw(st.lists(st.integers(1, 4), max_size=2)))
    spec = NetworkSpec(
        hidden=hidden,
        delays=draw(st.integers(0, 2)),
        recurrence=draw(st.integers(0, len(hidden) + 1)),
        output_activation=draw(st.sampled_from(["sigmoid", "linear"])),
    )
    finite = st.floats(allow_nan=False, allow_infinity=False)
    weights = draw(st.lists(finite, min_size=spec.weight_count, max_size=spec.weight_count))
    fitness = draw(st.none() | finite)
    provenance = draw(
        st.dictionaries(
            st.text(max_size=8),
            st.none() | st.text(max_size=8) | st.integers() | finite,
            max_size=4,
        )
    )
    return ControllerDocument(spec, np.array(weights), fitness, provenance)


def _doc() -> ControllerDocument:
    spec = PRESETS["paper-best"]
    w = np.random.default_rng(0).normal(size=spec.weight_count)
    return ControllerDocument(spec, w, 41.25, {"run": "r1", "generation": 349, "note": None})


@settings(max_examples=60, deadline=None)
@given(doc=documents())
def test_round_trip_is_byte_identical(doc: ControllerDocument) -> None:
    text = doc.to_json()
    back = ControllerDocument.from_json(text)
    assert back.sha256 == doc.sha256
    assert back.to_json() == text
    assert np.array_equal(back.weights, doc.weights)
    assert back == doc
    assert ControllerDocument.from_json(text.encode("utf-8")).to_json() == text
    assert ControllerDocument.from_dict(json.loads(text)).to_json() == text


def test_document_layout_and_hash_definition() -> None:
    doc = _doc()
    obj = json.loads(doc.to_json())
    assert obj["format"] == FORMAT == "evocolony.controller/1"
    assert obj["weights"]["dtype"] == "<f8" and obj["weights"]["shape"] == [222]
    raw = base64.b64decode(obj["weights"]["data"])
    assert np.array_equal(np.frombuffer(raw, dtype="<f8"), doc.weights)
    spec_json = json.dumps(obj["spec"], sort_keys=True, separators=(",", ":"))
    expected = hashlib.sha256(spec_json.encode() + b"\n" + raw).hexdigest()
    assert obj["sha256"] == doc.sha256 == controller_sha256(doc.spec, doc.weights) == expected
    assert doc.to_json() == json.dumps(obj, sort_keys=True, separators=(",", ":"))


def test_weights_are_a_read_only_copy() -> None:
    w = np.zeros(PRESETS["paper-best"].weight_count)
    doc = ControllerDocument(PRESETS["paper-best"], w)
    w[0] = 1.0
    assert doc.weights[0] == 0.0
    with pytest.raises(ValueError, match="read-only"):
        doc.weights[0] = 2.0


def test_spec_is_part_of_the_id() -> None:
    """Same weight count, different structure: different ids."""
    a = NetworkSpec(inputs=5, hidden=(), outputs=2, delays=1)
    b = NetworkSpec(inputs=5, hidden=(), outputs=2, delays=1, output_activation="linear")
    w = np.ones(a.weight_count)
    assert a.weight_count == b.weight_count
    assert controller_sha256(a, w) != controller_sha256(b, w)


def test_fitness_and_provenance_do_not_change_the_id() -> None:
    doc = _doc()
    other = ControllerDocument(doc.spec, doc.weights, None, {})
    assert other.sha256 == doc.sha256
    assert other != doc


def test_tampering_one_weight_bit_changes_the_hash_and_is_rejected() -> None:
    doc = _doc()
    obj = doc.to_dict()
    raw = bytearray(base64.b64decode(obj["weights"]["data"]))
    raw[17] ^= 0x01
    obj["weights"]["data"] = base64.b64encode(bytes(raw)).decode()
    tampered = np.frombuffer(bytes(raw), dtype="<f8")
    assert controller_sha256(doc.spec, tampered) != doc.sha256
    with pytest.raises(ControllerDocumentError, match="sha256 mismatch"):
        ControllerDocument.from_dict(obj)


def _with(**changes: Any) -> str:
    obj = _doc().to_dict()
    for key, value in changes.items():
        if key.startswith("weights_"):
            obj["weights"][key.removeprefix("weights_")] = value
        elif value is ...:
            del obj[key]
        else:
            obj[key] = value
    return json.dumps(obj)


def _nan_weights() -> str:
    w = _doc().weights.copy()
    w[3] = np.nan
    return base64.b64encode(w.astype("<f8").tobytes()).decode()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{not json", "invalid JSON"),
        (b"\xff\xfe", "invalid JSON"),
        ("[1, 2]", "is a JSON object"),
        (_with(format="evocolony.controller/2"), "unknown format"),
        (_with(spec={"hidden": [0]}), "invalid spec"),
        (_with(spec={"inputs": 5, "bogus": 1}), "invalid spec"),
        (_with(weights_dtype="<f4"), "dtype must be '<f8'"),
        (_with(weights_shape=[221]), "does not match the spec's 222 weights"),
        (_with(weights_data="!!!"), "not valid base64"),
        (_with(weights_data=base64.b64encode(b"12345678").decode()), "needs 1776"),
        (_with(weights_data=_nan_weights()), r"finite \(NaN/inf\): weight 3 is nan"),
        (_with(sha256="0" * 64), "sha256 mismatch"),
        (_with(fitness=float("nan")), "non-finite fitness"),
        (_with(fitness=float("inf")), "non-finite fitness"),
        (_with(fitness="high"), "fitness must be a number"),
        (_with(provenance={"run": [1]}), "provenance 'run' must be a string"),
        (_with(sha256=...), r"missing fields \['sha256'\]"),
        (_with(extra=1), r"unknown fields \['extra'\]"),
    ],
)
def test_bad_documents_are_refused_with_a_message(text: str | bytes, message: str) -> None:
    with pytest.raises(ControllerDocumentError, match=message):
        ControllerDocument.from_json(text)


def test_direct_construction_checks_its_arguments() -> None:
    spec = PRESETS["paper-best"]
    with pytest.raises(ValueError, match=r"shape \(222,\)"):
        ControllerDocument(spec, np.zeros(10))
    with pytest.raises(ValueError, match="weights must be finite"):
        ControllerDocument(spec, np.full(222, np.inf))
    with pytest.raises(ValueError, match="fitness must be finite"):
        ControllerDocument(spec, np.zeros(222), float("nan"))
    with pytest.raises(ValueError, match="provenance keys must be strings"):
        ControllerDocument(spec, np.zeros(222), None, {1: "x"})  # type: ignore[dict-item]
