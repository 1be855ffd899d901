"""Wire codecs (protocol 11): every message round-trips bit for bit, and every malformed
payload raises WireError (never anything else)."""

from __future__ import annotations

import contextlib
import math
import re
import struct
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from pydantic import BaseModel

from evorobotics.evolution import RunLoop
from schemas.run import RunConfig
from schemas.wire import (
    ERROR_MAX,
    KEY_JOB_NEXT,
    KEY_JOB_RESULT,
    KEY_WORKERS,
    PROTOCOL,
    SPAN_BATCH_MAX,
    Ack,
    Idle,
    InvalidJobError,
    Job,
    JobKey,
    JobRequest,
    Result,
    WireError,
    check_worker_name,
    decode,
    decode_frame,
    decode_job,
    decode_next_reply,
    decode_result_reply,
    encode,
    encode_frame,
    genome_digest,
    next_key,
    result_key,
    worker_key,
)

CONFIG = RunConfig(population=10, job_size=4, generations=3, trials=2)
W = CONFIG.network_spec.weight_count
KEY = JobKey(run_id=3, generation=1, index=1)
MODELS: tuple[type[Any], ...] = (JobRequest, Idle, Ack, Job, Result)


def make_job(rows: int = 4, start: int = 4, **fields: Any) -> Job:
    genomes = np.arange(rows * W, dtype=np.float64).reshape(rows, W) / 7.0
    return Job(key=KEY, start=start, stop=start + rows, lease_s=12.5, config=CONFIG,
               genomes=genomes, **fields)  # fmt: skip


def span_job(span: int = 2) -> Job:
    loop = RunLoop(CONFIG)
    loop.tell(np.arange(10.0))  # generation 1: the state has a ranked population
    key = KEY.model_copy(update={"index": 0})
    return Job(key=key, start=0, stop=10, config=CONFIG, genomes=np.array(loop.ask()),
               span=span, state=loop.state.to_arrays())  # fmt: skip


def make_result(k: int = 1, n: int = 4, seed: int = 0, **fields: Any) -> Result:
    rng = np.random.default_rng(seed)
    values: dict[str, Any] = {
        "key": KEY,
        "worker": "w-1",
        "start": 4,
        "stop": 4 + n,
        "robot_steps_per_s": 2.5e6,
        "seconds": 0.01,
        "fitness": rng.normal(size=(k, n)),
        "components": rng.normal(size=(k, n, CONFIG.trials, 4)),
        "descriptors": rng.uniform(size=(k, n, 4)),
    }
    return Result(**(values | fields))


def assert_same(sent: BaseModel, back: BaseModel) -> None:
    """Equal fields, and every array (a Job's state arrays too) equal byte for byte."""
    arrays: tuple[str, ...] = type(sent).ARRAYS  # type: ignore[attr-defined]
    assert type(back) is type(sent)
    assert back.model_dump(exclude=set(arrays)) == sent.model_dump(exclude=set(arrays))
    for name in arrays:
        a, b = getattr(sent, name), getattr(back, name)
        if isinstance(a, dict):
            assert isinstance(b, dict) and a.keys() == b.keys()
            pairs = [(a[k], b[k]) for k in a]
        else:
            pairs = [(a, b)]
        for x, y in pairs:
            if x is None:
                assert y is None
                continue
            assert (x.dtype, x.shape) == (y.dtype, y.shape) and x.tobytes() == y.tobytes()


# ---------------------------------------------------------------------------------- frames


@given(
    shape=st.lists(st.integers(0, 5), min_size=0, max_size=3),
    dtype=st.sampled_from(["<f8", "<f4", "<i8", "<i4", "|u1", "|b1", ">f8"]),
    seed=st.integers(0, 2**32 - 1),
)
@settings(max_examples=60, deadline=None)
def test_frame_round_trips_arrays_bit_exact(shape: list[int], dtype: str, seed: int) -> None:
    raw = np.random.default_rng(seed).normal(size=shape) * 100
    array = raw.astype(dtype)
    header, arrays = decode_frame(encode_frame({"x": 1}, {"a": array, "b": np.ones(2)}))
    assert header == {"x": 1}
    assert arrays["a"].shape == array.shape
    assert arrays["a"].tobytes() == array.astype(array.dtype.newbyteorder("<")).tobytes()
    assert np.array_equal(arrays["a"], array)
    assert np.array_equal(arrays["b"], np.ones(2))


def test_a_frame_refuses_object_arrays_and_its_reserved_key() -> None:
    with pytest.raises(ValueError, match="dtype"):
        encode_frame({}, {"a": np.array(["x"], dtype=object)})
    with pytest.raises(ValueError, match="reserved"):
        encode_frame({"arrays": []})


# ------------------------------------------------------------------------------ round trips


def test_the_protocol_and_its_keys() -> None:
    assert PROTOCOL == 16 and JobRequest(worker="w").protocol == PROTOCOL
    assert (next_key("w"), result_key("w")) == ("evocolony/jobs/next/w", "evocolony/jobs/result/w")
    assert next_key("w-1").startswith(KEY_JOB_NEXT.removesuffix("*"))
    assert result_key("w-1").startswith(KEY_JOB_RESULT.removesuffix("*"))
    assert worker_key("w-1").startswith(KEY_WORKERS.removesuffix("*"))


def test_a_job_round_trips_bit_exact() -> None:
    job = make_job()
    back = decode_next_reply(encode(job))
    assert isinstance(back, Job)
    assert_same(job, back)
    assert (back.key, back.start, back.stop, back.lease_s) == (KEY, 4, 8, 12.5)
    assert back.config == CONFIG and (back.span, back.state, back.ack) == (1, None, None)
    assert_same(job, decode_job(encode(job)))
    assert_same(job, decode(encode(job), Job))


def test_a_span_job_round_trips_with_its_ga_state() -> None:
    job = span_job()
    back = decode_next_reply(encode(job))
    assert isinstance(back, Job) and back.span == 2 and back.state is not None
    assert_same(job, back)
    assert job.state is not None and set(back.state) == set(job.state)
    assert {"generation", "n_weights", "ranked", "ranked_fitness"} <= set(back.state)


def test_a_result_reply_is_an_ack_or_the_next_job_carrying_it() -> None:
    ack = Ack(key=KEY, accepted=True)
    assert decode_result_reply(encode(ack)) == (ack, None)
    refused = Ack(key=KEY, accepted=False, reason="no lease held: late or duplicate")
    assert decode_result_reply(encode(refused)) == (refused, None)
    job = make_job(start=0).model_copy(update={"key": KEY.at(2), "ack": ack})
    got_ack, got_job = decode_result_reply(encode(job))
    assert got_ack == ack and got_job is not None
    assert_same(job, got_job)
    assert got_job.ack == ack
    span = span_job().model_copy(update={"ack": ack})
    _, got_span = decode_result_reply(encode(span))
    assert got_span is not None
    assert_same(span, got_span)


@pytest.mark.parametrize("k", [1, 5, SPAN_BATCH_MAX])
def test_a_result_of_k_generations_with_digests_round_trips_bit_exact(k: int) -> None:
    digests = tuple(genome_digest(np.full((4, W), float(g))) for g in range(k))
    result = make_result(k, seed=k, digests=digests, want_next=True)
    back = decode(encode(result), Result)
    assert_same(result, back)
    assert back.generations == k and back.digests == digests and back.want_next
    plain = make_result()
    assert_same(plain, decode(encode(plain), Result))
    assert plain.generations == 1 and plain.digests == ()


@given(
    fitness=hnp.arrays(
        np.float64,
        st.tuples(st.integers(1, 4), st.integers(1, 5)),
        elements=st.floats(allow_nan=False, allow_infinity=False),
    ),
    seed=st.integers(0, 2**32 - 1),
)
@settings(max_examples=60, deadline=None)
def test_results_of_any_finite_values_round_trip_bit_exact(fitness: np.ndarray, seed: int) -> None:
    """Signed zeros, subnormals, the extremes: what the worker computed is what is stored."""
    k, n = fitness.shape
    rng = np.random.default_rng(seed)
    components = rng.normal(size=(k, n, 1, 4)) * 1e300
    descriptors = rng.uniform(size=(k, n, 4))
    result = Result(
        key=KEY,
        worker="w",
        start=0,
        stop=n,
        fitness=fitness,
        components=components,
        descriptors=descriptors,
    )
    assert_same(result, decode(encode(result), Result))


def test_an_error_result_and_the_control_messages_round_trip() -> None:
    error = Result(key=KEY, worker="w-1", error="boom", start=4, stop=8, seconds=0.5)
    assert_same(error, decode(encode(error), Result))
    assert error.generations == 1 and error.fitness is None
    unsliced = Result(key=KEY, worker="w-1", error="bad job")  # a job whose slice did not parse
    assert_same(unsliced, decode(encode(unsliced), Result))
    messages: list[JobRequest | Idle | Ack] = [
        JobRequest(worker="w-1", host="lab-pc", robot_steps_per_s=1234.5),
        JobRequest(worker="w-1"),
        JobRequest(worker="w-1", protocol=9),
        Idle(),
        Idle(reason="no job"),
        Ack(key=KEY, accepted=True),
        Ack(key=KEY, accepted=False, reason="late"),
    ]
    for message in messages:
        assert decode(encode(message), type(message)) == message
    assert decode_next_reply(encode(Idle(reason="x"))) == Idle(reason="x")


def test_numbers_as_numpy_computes_them_are_written_as_json_numbers() -> None:
    numbers: dict[str, Any] = {
        "robot_steps_per_s": np.float64(3.5),
        "seconds": np.float32(0.25),
        "start": np.int64(0),
        "stop": np.int64(2),
    }
    back = decode(encode(Result(key=KEY, worker="w", error="e", **numbers)), Result)
    assert (back.robot_steps_per_s, back.seconds, back.start, back.stop) == (3.5, 0.25, 0, 2)


def test_job_keys() -> None:
    assert KEY.at(5) == JobKey(run_id=3, generation=5, index=1)
    assert KEY.label() == "run 3 gen 1 job 1"
    for bad in ({"run_id": -1}, {"generation": 2**63}, {"index": 1.5}):
        with pytest.raises(ValueError):
            KEY.model_validate(KEY.model_dump() | bad)


# ---------------------------------------------------------------------------- bad messages


def test_a_result_refuses_non_finite_or_negative_speeds_and_times() -> None:
    for speed, seconds in ((math.nan, 0.0), (math.inf, 0.0), (-1.0, 0.0), (0.0, math.inf)):
        with pytest.raises(ValueError):
            Result(key=KEY, worker="w", error="boom", robot_steps_per_s=speed, seconds=seconds)
        with pytest.raises(ValueError):
            make_result(robot_steps_per_s=speed, seconds=seconds)
    for speed in (math.nan, -math.inf, -1.0):
        with pytest.raises(ValueError):
            JobRequest(worker="w", robot_steps_per_s=speed)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"fitness": np.zeros(4)}, "float64"),  # 1-D: k missing
        ({"fitness": np.array(0.0)}, "float64"),  # 0-d
        ({"fitness": np.zeros((1, 4), np.float32)}, "float64"),
        ({"fitness": np.zeros((0, 4)), "components": np.zeros((0, 4, 2, 4))}, "k <="),
        (
            {
                "fitness": np.zeros((SPAN_BATCH_MAX + 1, 4)),
                "components": np.zeros((SPAN_BATCH_MAX + 1, 4, 2, 4)),
            },
            "k <=",
        ),
        ({"fitness": np.zeros((1, 3))}, "slice and checks: 4"),
        ({"components": np.zeros((1, 3, 2, 4))}, "components"),
        ({"components": np.zeros((2, 4, 2, 4))}, "components"),
        ({"components": np.zeros((1, 4, 2))}, "components"),
        ({"components": None}, "needs its slice"),
        ({"descriptors": None}, "descriptors"),
        ({"descriptors": np.zeros((1, 4, 3))}, "descriptors"),
        ({"descriptors": np.zeros((1, 4, 4), dtype=np.float32)}, "descriptors"),
        ({"start": None, "stop": None}, "needs its slice"),
        ({"start": 4, "stop": 4}, "bad slice"),
        ({"stop": None}, "bad slice"),
        ({"digests": ("0BADCAFE",)}, "digests"),
        ({"digests": ("0badcaf",)}, "digests"),
        ({"digests": ("0" * 64,)}, "digests"),
        ({"digests": ("0badcafe", "0badcafe")}, "2 digests for 1"),
        ({"error": "boom"}, "carries no fitness"),
        ({"worker": "a/b"}, "worker"),
    ],
)
def test_a_result_refuses_what_the_server_would_refuse(
    fields: dict[str, Any], message: str
) -> None:
    """Caught where the result is built (ValueError) and where it is decoded (WireError)."""
    with pytest.raises(ValueError, match=message):
        make_result(**fields)
    good = make_result()
    header, arrays = decode_frame(encode(good))
    for name, value in fields.items():
        if name in Result.ARRAYS:
            arrays.pop(name)
            if value is not None:
                arrays[name] = value
        else:
            header[name] = value
    with pytest.raises(WireError, match=message):
        decode(encode_frame(header, arrays), Result)


def test_a_result_carries_impossible_values_for_the_scheduler_to_judge() -> None:
    """Non-finite fitness and descriptors outside [0, 1] are claims, not structure: they decode
    bit for bit, so the scheduler refuses them as a forgery (`evorobotics.evaluate.implausible`)
    and quarantines the credential, instead of dropping them as malformed."""
    descriptors = np.full((1, 4, 4), 0.5)
    descriptors[0, 0] = (1.5, -0.5, np.nan, np.inf)
    fitness = np.array([[np.nan, np.inf, -np.inf, 1.7e308]])
    forged = make_result(fitness=fitness, descriptors=descriptors)
    assert_same(forged, decode(encode(forged), Result))


def test_an_error_result_carries_no_digests() -> None:
    with pytest.raises(ValueError, match="carries no fitness"):
        Result(key=KEY, worker="w", error="boom", digests=("0badcafe",))


def test_error_text_is_cut_to_error_max_and_made_valid_utf8() -> None:
    """An exception's text of any length or encoding still reaches the server."""
    huge = decode(encode(Result(key=KEY, worker="w", error="x" * (ERROR_MAX + 10))), Result)
    assert huge.error is not None and len(huge.error) == ERROR_MAX
    assert huge.error.startswith("x" * 100) and huge.error.endswith("\u2026")
    exact = Result(key=KEY, worker="w", error="y" * ERROR_MAX)
    assert exact.error == "y" * ERROR_MAX
    odd = decode(encode(Result(key=KEY, worker="w", error="bad name \udcff here")), Result)
    assert odd.error == "bad name ? here"
    odd.error.encode("utf-8")  # valid UTF-8: no surrogate left


def frame(head: bytes, body: bytes = b"") -> bytes:
    """A frame by hand: magic, the header's true length, the header, the body."""
    return b"EVC1" + struct.pack("<I", len(head)) + head + body


BAD_FRAMES = [
    b"",
    b"EVC",
    b"XXXX" + struct.pack("<I", 2) + b"{}",
    b"EVC1" + struct.pack("<I", 100) + b"{}",
    b"EVC1" + struct.pack("<I", 2**31) + b"{}",
    frame(b"[]"),
    frame(b"\xff\xfe{"),
    frame(b"{}"),
    frame(b'{"arrays":{}}'),
    frame(b'{"arrays":[1]}'),
    frame(b'{"arrays":[],"x":1e999}'),
    encode_frame({"kind": "job"}) + b"trailing",
    frame(b'{"arrays":[{"name":"a","dtype":"|O","shape":[1]}]}', b"\0" * 8),
    frame(b'{"arrays":[{"name":"a","dtype":"<f8","shape":[9]}]}', b"\0" * 8),
    frame(b'{"arrays":[{"name":"a","dtype":"<f8","shape":[-1]}]}'),
    frame(b'{"arrays":[{"name":"a","dtype":["<f8"],"shape":[]}]}'),
    frame(b'{"arrays":[{"name":"a","dtype":"<f8","shape":[true]}]}', b"\0" * 8),
    frame(b'{"arrays":[{"name":"a","dtype":"<f8","shape":[1,1,1,1,1,1,1,1,1]}]}', b"\0" * 8),
]
BAD_MESSAGES = [
    encode_frame({"kind": "job"}),
    encode_frame({"kind": "idle", "reason": 5}),
    encode_frame({"kind": "ack", "key": {"run_id": 1}, "accepted": True}),
    encode_frame({"kind": "next", "worker": "w", "robot_steps_per_s": None, "bogus": 1}),
    encode_frame({"kind": "result", "key": KEY.model_dump(), "worker": "w", "error": None}),
    encode(Ack(key=KEY, accepted=True)).replace(b'"kind":"ack"', b'"kind":"job"'),
]


def decoders() -> list[Any]:
    """Every way a payload is decoded: each model, and the job and reply decoders."""
    models = [lambda p, m=model: decode(p, m) for model in MODELS]
    return [*models, decode_job, decode_next_reply, decode_result_reply]


@pytest.mark.parametrize("payload", BAD_FRAMES)
def test_malformed_frames_raise_wire_error(payload: bytes) -> None:
    with pytest.raises(WireError):
        decode_frame(payload)
    for decoder in decoders():
        with pytest.raises(WireError):
            decoder(payload)


@pytest.mark.parametrize("payload", BAD_MESSAGES)
def test_frames_of_no_valid_message_raise_wire_error(payload: bytes) -> None:
    decode_frame(payload)  # the frame itself is fine
    for decoder in decoders():
        with pytest.raises(WireError):
            decoder(payload)


@pytest.mark.parametrize(
    "arrays",
    [
        {"genomes": np.zeros((4, W)), "genomes.x": np.zeros(1)},  # an array and a group
        {"genomes.x": np.zeros(1), "genomes": np.zeros((4, W))},
        {"genomes": np.zeros((4, W)), "state.": np.zeros(1)},  # a group member without a name
        {"genomes": np.zeros((4, W)), "bogus": np.zeros(1)},
    ],
)
def test_arrays_that_clash_or_stray_are_invalid_jobs(arrays: dict[str, np.ndarray]) -> None:
    header = decode_frame(encode(make_job(start=0)))[0]
    with pytest.raises(InvalidJobError) as caught:
        decode_job(encode_frame(header, arrays))
    assert caught.value.key == KEY


@pytest.mark.parametrize("value", [[1], "ab", 5, None, {"x": 1}])
def test_an_array_field_given_in_the_header_is_refused(value: object) -> None:
    """A frame whose header also holds an array field (or a group) is malformed, not a crash."""
    job = span_job()
    assert job.state is not None
    header, arrays = decode_frame(encode(job))
    for name in ("state", "genomes"):
        with pytest.raises(WireError):
            decode_job(encode_frame({**header, name: value}, arrays))
    result_header, result_arrays = decode_frame(encode(make_result()))
    for bad in ({**result_arrays, "fitness.x": np.zeros(1)}, {"fitness.x": np.zeros(1)}):
        with pytest.raises(WireError):
            decode(encode_frame({**result_header, "fitness": value}, bad), Result)


@given(st.binary(max_size=300))
@settings(max_examples=200, deadline=None)
def test_arbitrary_bytes_never_raise_anything_but_wire_error(payload: bytes) -> None:
    for decoder in decoders():
        with contextlib.suppress(WireError):
            decoder(payload)


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=10),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner),
    max_leaves=6,
)
FIELDS = ["kind", "key", "start", "stop", "config", "span", "state", "ack", "genomes"]
FIELDS += ["fitness", "digests", "worker", "error", "lease_s", "robot_steps_per_s", "x"]
FIELDS = ["kind", "key", "start", "stop", "config", "span", "state", "ack", "genomes"]
FIELDS += ["fitness", "digests", "worker", "error", "lease_s", "robot_steps_per_s", "x"]
TEMPLATES = [
    encode(make_job()),
    encode(span_job().model_copy(update={"ack": Ack(key=KEY, accepted=True)})),
    encode(make_result(2, digests=("0badcafe", "12345678"))),
    encode(Result(key=KEY, worker="w", error="boom")),
    encode(JobRequest(worker="w", robot_steps_per_s=3.0)),
    encode(Ack(key=KEY, accepted=True)),
    encode(Idle()),
]


@given(
    template=st.sampled_from(TEMPLATES),
    changes=st.dictionaries(st.sampled_from(FIELDS), json_values, min_size=1, max_size=3),
    arrays=st.lists(
        st.tuples(
            st.sampled_from(["genomes", "state.ranked", "state", "fitness", "components", "x"]),
            st.sampled_from(["<f8", "<i8", "|b1"]),
            st.lists(st.integers(0, 3), max_size=3),
        ),
        max_size=2,
    ),
)
@settings(max_examples=150, deadline=None)
def test_valid_messages_with_fields_replaced_raise_only_wire_error(
    template: bytes, changes: dict[str, Any], arrays: list[tuple[str, str, list[int]]]
) -> None:
    header, body = decode_frame(template)
    body |= {name: np.zeros(shape, dtype) for name, dtype, shape in arrays}
    payload = encode_frame(header | changes, body)
    for decoder in decoders():
        with contextlib.suppress(WireError):
            decoder(payload)


# ----------------------------------------------------------------------------- invalid jobs


def test_invalid_job_content_carries_its_key() -> None:
    job = make_job()
    bad = job.genomes.copy()
    bad[0, 0] = np.nan
    frame = encode(job).replace(job.genomes.tobytes(), bad.tobytes())
    with pytest.raises(InvalidJobError, match="NaN") as caught:
        decode_job(frame)
    assert caught.value.key == KEY and caught.value.ack is None
    header = decode_frame(encode(job))[0]
    wrong_rows = encode_frame(header, {"genomes": np.zeros((3, W))})
    with pytest.raises(InvalidJobError, match="expected float64") as caught:
        decode_next_reply(wrong_rows)
    assert caught.value.key == KEY
    bad_config = encode_frame({**header, "config": {"population": -5}}, {"genomes": job.genomes})
    with pytest.raises(InvalidJobError, match="config") as caught:
        decode_job(bad_config)
    assert caught.value.key == KEY
    head = (  # valid JSON, a config nested deeper than orjson writes back
        b'{"kind":"job","key":{"run_id":3,"generation":1,"index":1},"start":0,"stop":4,'
        b'"lease_s":1.0,"config":' + b"[" * 300 + b"0" + b"]" * 300 + b',"arrays":[{"name":'
        b'"genomes","dtype":"<f8","shape":[4,' + str(W).encode() + b"]}]}"
    )
    deep = b"EVC1" + struct.pack("<I", len(head)) + head + np.zeros((4, W)).tobytes()
    with pytest.raises(InvalidJobError, match="config") as caught:
        decode_job(deep)
    assert caught.value.key == KEY
    outside = encode_frame({**header, "start": 8, "stop": 12}, {"genomes": job.genomes})
    with pytest.raises(InvalidJobError, match="outside population"):
        decode_job(outside)
    with pytest.raises(ValueError, match="outside population"):
        make_job(start=8)
    unkeyed = encode_frame({**header, "key": {"run_id": "x"}}, {"genomes": job.genomes})
    with pytest.raises(WireError) as plain:
        decode_job(unkeyed)
    assert not isinstance(plain.value, InvalidJobError)


def test_an_invalid_next_job_after_a_result_carries_the_ack() -> None:
    ack = Ack(key=KEY.at(0), accepted=True)
    job = make_job().model_copy(update={"ack": ack})
    header, arrays = decode_frame(encode(job))
    with pytest.raises(InvalidJobError, match="slice") as caught:
        decode_result_reply(encode_frame({**header, "start": 9}, arrays))
    assert caught.value.ack == ack and caught.value.key == KEY
    no_ack = encode_frame({**header, "ack": {**header["ack"], "accepted": "maybe"}}, arrays)
    with pytest.raises(WireError, match="Ack"):
        decode_result_reply(no_ack)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"span": 3}, "passes 3"),  # generation 1 + 3 > CONFIG.generations
        ({"state": None}, "GA state"),
        ({"span": 1}, "GA state"),
        ({"start": 2, "genomes": np.zeros((8, W))}, "whole population"),
        ({"genomes": np.zeros((10, W + 1))}, "expected float64"),
        ({"lease_s": 0.0}, "lease_s"),
    ],
)
def test_a_span_must_fit_the_run_and_bring_its_state(
    change: dict[str, object], message: str
) -> None:
    fields = span_job().model_dump() | change
    with pytest.raises(ValueError, match=message):
        Job(**fields)
    header, arrays = decode_frame(encode(span_job()))
    for name, value in change.items():
        if name == "genomes":
            arrays["genomes"] = value  # type: ignore[assignment]
        elif name == "state":
            arrays = {k: v for k, v in arrays.items() if not k.startswith("state.")}
        else:
            header[name] = value
    with pytest.raises(InvalidJobError, match=message) as caught:
        decode_job(encode_frame(header, arrays))
    assert caught.value.key == span_job().key


# ------------------------------------------------------------------------ names and digests


def test_worker_names_are_single_key_chunks() -> None:
    assert worker_key("lab-pc.3_a") == "evocolony/workers/lab-pc.3_a"
    assert check_worker_name("x" * 128) == "x" * 128
    for bad in ("", "a/b", "a*", "x" * 129, "a b", "$", "**", "a?b", "é", "a\nb"):
        with pytest.raises(ValueError):
            worker_key(bad)
        with pytest.raises(ValueError):
            check_worker_name(bad)
        with pytest.raises(ValueError):
            JobRequest(worker=bad)
        with pytest.raises(ValueError):
            Result(key=KEY, worker=bad, error="e")
        with pytest.raises(WireError):
            decode(encode_frame({"kind": "next", "worker": bad}), JobRequest)


def test_genome_digest_sees_any_changed_bit_and_any_reordering() -> None:
    genomes = np.random.default_rng(1).normal(size=(10, W))
    assert re.fullmatch("[0-9a-f]{8}", genome_digest(genomes))
    assert genome_digest(genomes) == genome_digest(genomes.copy(order="F"))
    assert genome_digest(genomes.astype(">f8")) == genome_digest(genomes)
    for row, column, bit in ((0, 0, 0), (3, 7, 63), (9, W - 1, 31)):
        changed = genomes.copy()
        changed.view(np.uint64)[row, column] ^= np.uint64(1 << bit)
        assert genome_digest(genomes) != genome_digest(changed)
    swapped = genomes[[1, 0, *range(2, 10)]]
    assert genome_digest(genomes) != genome_digest(swapped)
    assert genome_digest(genomes[:, :5]) != genome_digest(genomes[:5, :].T)
    make_result(digests=(genome_digest(genomes),))  # a valid digest for a Result


# ------------------------------------------------------------------------- champion stages

CHAMPION = CONFIG.model_copy(
    update={"validation": CONFIG.validation.model_copy(update={"candidates": 6, "test_poses": 9})}
)


def stage_job(stage: str, start: int, stop: int, rows: int) -> Job:
    key = JobKey(run_id=3, generation=CHAMPION.generations - 1, index=0, stage=stage)
    genomes = np.arange(rows * W, dtype=np.float64).reshape(rows, W) / 7.0
    return Job(key=key, start=start, stop=stop, config=CHAMPION, genomes=genomes)


def stage_result(stage: str, scores: np.ndarray, start: int = 0) -> Result:
    key = JobKey(run_id=3, generation=CHAMPION.generations - 1, index=0, stage=stage)
    return Result(key=key, worker="w-1", start=start, stop=start + len(scores), scores=scores)


def test_champion_stage_jobs_and_results_round_trip_bit_exact() -> None:
    validate = stage_job("validate", 2, 5, rows=3)
    test = stage_job("test", 0, 9, rows=1)
    for job in (validate, test):
        back = decode_next_reply(encode(job))
        assert isinstance(back, Job) and back.key.stage == job.key.stage
        assert_same(job, back)
    assert "validate job 0" in validate.key.label() and "train" not in KEY.label()
    scored = stage_result("validate", np.array([[3.5, 0.25, 0.5], [-1.0, 0.0, 1.0]]))
    trials = stage_result("test", np.array([[1.0, 0.0, 0.0, 1.0, 2.5, 0.1]]), start=4)
    for result in (scored, trials):
        assert_same(result, decode(encode(result), Result))


@pytest.mark.parametrize(
    ("stage", "start", "stop", "rows", "message"),
    [
        ("validate", 4, 7, 3, "outside 6"),
        ("validate", 0, 3, 2, "expected float64"),
        ("test", 8, 10, 1, "outside 9"),
        ("test", 0, 3, 3, "expected float64"),
    ],
)
def test_a_champion_stage_job_must_fit_its_validation(
    stage: str, start: int, stop: int, rows: int, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        stage_job(stage, start, stop, rows)


def test_a_champion_stage_job_is_of_the_last_generation_and_no_span() -> None:
    job = stage_job("validate", 0, 2, rows=2)
    with pytest.raises(ValueError, match="last generation"):
        job.model_validate(job.model_dump() | {"key": job.key.model_copy(update={"generation": 0})})
    with pytest.raises(ValueError, match="no span"):
        job.model_validate(job.model_dump() | {"span": 2})


@pytest.mark.parametrize(
    ("stage", "scores", "message"),
    [
        ("validate", np.array([[1.0, 1.5, 0.0]]), r"\[0, 1\]"),
        ("validate", np.array([[np.nan, 0.0, 0.0]]), "finite"),
        ("validate", np.zeros((1, 6)), "float64"),
        ("test", np.array([[0.5, 0.0, 0.0, 0.0, 1.0, 1.0]]), "0 or 1"),
        ("test", np.array([[0.0, 0.0, 0.0, 0.0, -1.0, 1.0]]), "offset"),
        ("test", np.array([[0.0, 0.0, 0.0, 0.0, 1.0, 2e6]]), "offset"),
    ],
)
def test_a_champion_stage_result_refuses_impossible_scores(
    stage: str, scores: np.ndarray, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        stage_result(stage, scores)


def test_a_stage_result_carries_scores_only_and_a_training_result_none() -> None:
    key = JobKey(run_id=3, generation=CHAMPION.generations - 1, index=0, stage="validate")
    with pytest.raises(ValueError, match="scores only"):
        make_result(key=key, scores=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="no scores"):
        make_result(scores=np.zeros((4, 3)))


def test_validation_off_refuses_its_stages_jobs_and_a_stage_is_one_of_five() -> None:
    v = CHAMPION.validation.model_copy(update={"poses": 0, "test_poses": 0})
    off = CHAMPION.model_copy(update={"validation": v})
    for stage, rows in (("validate", 2), ("test", 1)):
        key = JobKey(run_id=3, generation=off.generations - 1, index=0, stage=stage)
        with pytest.raises(ValueError, match="outside 0"):
            Job(key=key, start=0, stop=rows, config=off, genomes=np.zeros((rows, W)))
    with pytest.raises(ValueError, match="stage"):
        JobKey.model_validate({"run_id": 3, "generation": 1, "index": 0, "stage": "tune"})
    assert JobKey(run_id=3, generation=1, index=0).stage == "train"


def test_a_stage_result_carries_a_row_per_slice_member_and_an_error_none() -> None:
    with pytest.raises(ValueError, match=r"float64\(2, 3\)"):
        stage_result("validate", np.zeros((2, 6)))
    key = JobKey(run_id=3, generation=CHAMPION.generations - 1, index=0, stage="test")
    with pytest.raises(ValueError, match="needs its slice"):
        Result(key=key, worker="w-1", scores=np.zeros((1, 6)))
    with pytest.raises(ValueError, match="no fitness"):
        Result(key=key, worker="w-1", start=0, stop=1, error="boom", scores=np.zeros((1, 6)))
    erred = Result(key=key, worker="w-1", start=0, stop=1, error="boom")
    assert_same(erred, decode(encode(erred), Result))
