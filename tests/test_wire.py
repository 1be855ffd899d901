"""Wire codecs: round trips, and every malformed payload raises WireError (never anything else)."""

from __future__ import annotations

import contextlib
import math
import struct
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.run import RunConfig
from schemas.wire import (
    ERROR_MAX,
    Ack,
    Idle,
    InvalidJobError,
    Job,
    JobKey,
    JobRequest,
    Result,
    TeamMessage,
    WireError,
    decode_ack,
    decode_frame,
    decode_job,
    decode_next_reply,
    decode_request,
    decode_result,
    decode_result_reply,
    decode_results,
    decode_team_message,
    encode_frame,
    encode_job,
    encode_message,
    encode_result,
    encode_span_results,
    encode_team_message,
    genome_digest,
    team_cuts,
    worker_key,
)

CONFIG = RunConfig(population=10, job_size=4, generations=2)
W = CONFIG.network_spec.weight_count
KEY = JobKey(run_id=3, generation=7, index=1)


def make_job(rows: int = 4, start: int = 4) -> Job:
    genomes = np.arange(rows * W, dtype=np.float64).reshape(rows, W) / 7.0
    return Job(KEY, start, start + rows, CONFIG, genomes, lease_s=12.5)


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


def test_job_round_trip_is_bit_exact() -> None:
    job = make_job()
    back = decode_next_reply(encode_job(job))
    assert isinstance(back, Job)
    assert back.key == KEY and (back.start, back.stop, back.lease_s) == (4, 8, 12.5)
    assert back.config == CONFIG
    assert back.genomes.tobytes() == job.genomes.tobytes()
    assert back.robot_steps == 4 * CONFIG.trials * CONFIG.steps
    assert back.more  # the default: a prefetch may find another job
    last = decode_next_reply(encode_job(replace(job, more=False)))
    assert isinstance(last, Job) and not last.more


def test_a_leased_job_differs_only_in_its_lease_and_more() -> None:
    job = make_job()
    leased = job.leased(3.0, False)
    assert (leased.lease_s, leased.more, job.lease_s, job.more) == (3.0, False, 12.5, True)
    assert replace(leased, lease_s=job.lease_s, more=job.more) == job
    back = decode_next_reply(encode_job(leased))
    assert isinstance(back, Job) and (back.lease_s, back.more) == (3.0, False)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="lease_s"):
            job.leased(bad, True)


def test_result_and_control_round_trips() -> None:
    fitness = np.array([1.5, -2.0, 0.0])
    components = np.arange(3 * 3 * 4, dtype=np.float64).reshape(3, 3, 4)
    result = Result(KEY, "w-1", fitness, components, 1234.5, 0.25, start=4, stop=7)
    back = decode_result(encode_result(result))
    assert back.key == KEY and back.worker == "w-1" and back.error is None
    assert (back.start, back.stop) == (4, 7)
    assert back.fitness is not None and back.fitness.tobytes() == fitness.tobytes()
    assert back.components is not None and np.array_equal(back.components, components)
    err = decode_result(encode_result(Result(KEY, "w-1", error="boom")))
    assert err.error == "boom" and err.fitness is None
    request = JobRequest(worker="w-1", host="h", robot_steps_per_s=10.0)
    assert decode_request(encode_message(request)) == request
    other = KEY.model_copy(update={"index": KEY.index + 1})
    prefetch = JobRequest(worker="w-1", holding=(KEY, other))
    assert decode_request(encode_message(prefetch)).holding == (KEY, other)
    held = Result(KEY, "w-1", fitness, holding=(other,), start=0, stop=3)
    holding = decode_result(encode_result(held))
    assert holding.holding == (other,) and not holding.want_next
    ack = Ack(key=KEY, accepted=False, reason="late")
    assert decode_ack(encode_message(ack)) == ack
    assert decode_next_reply(encode_message(Idle())) == Idle()
    asking = decode_result(encode_result(held.asking(True, (KEY,))))
    assert asking.want_next and asking.holding == (KEY,) and asking.fitness is not None
    assert (asking.seq, asking.awaiting) == (0, ())  # unnumbered: as before protocol 9
    ahead = decode_result(encode_result(held.asking(True, (), seq=7, awaiting=(5, 6))))
    assert (ahead.seq, ahead.awaiting, ahead.holding) == (7, (5, 6), ())
    numbered = JobRequest(worker="w-1", seq=3, awaiting=(2,))
    assert decode_request(encode_message(numbered)) == numbered


def test_a_result_reaches_the_server_whatever_its_error_text_or_number_types() -> None:
    """An exception's text of any length or encoding still reaches the server (cut to what it
    accepts, made UTF-8); numpy scalars are written as JSON numbers."""
    huge = decode_result(encode_result(Result(KEY, "w-1", error="x" * (ERROR_MAX + 10))))
    assert huge.error is not None and len(huge.error) == ERROR_MAX
    assert huge.error.startswith("x" * 100) and huge.error.endswith("\u2026")
    odd = decode_result(encode_result(Result(KEY, "w-1", error="bad name \udcff here")))
    assert odd.error == "bad name ? here"
    numbers: dict[str, Any] = {  # as numpy computes them
        "robot_steps_per_s": np.float64(3.5),
        "seconds": np.float32(0.25),
        "start": np.int64(0),
        "stop": np.int64(2),
    }
    back = decode_result(encode_result(Result(KEY, "w-1", np.zeros(2), **numbers)))
    assert (back.robot_steps_per_s, back.seconds, back.start, back.stop) == (3.5, 0.25, 0, 2)


def test_a_result_refuses_what_the_server_would_refuse() -> None:
    """Caught where the result is built, not in a retry loop against the server's refusal: a
    NaN speed or time (written as null), a digest that is not CRC-32, too many held jobs."""
    for speed, seconds in ((math.nan, 0.0), (0.0, math.inf), (-1.0, 0.0)):
        with pytest.raises(WireError, match="finite"):
            Result(KEY, "w-1", error="boom", robot_steps_per_s=speed, seconds=seconds)
    with pytest.raises(WireError, match="digest"):
        Result(KEY, "w-1", np.zeros(2), start=0, stop=2, digest="0" * 64)
    many = tuple(KEY.model_copy(update={"index": i}) for i in range(17))
    with pytest.raises(WireError, match="holds 17"):
        Result(KEY, "w-1", error="boom", holding=many)
    with pytest.raises(WireError, match="holds 17"):
        Result(KEY, "w-1", error="boom").asking(True, many)
    with pytest.raises(WireError, match="awaits 17"):
        Result(KEY, "w-1", error="boom").asking(True, (), seq=18, awaiting=tuple(range(1, 18)))
    for seq, awaiting in ((2, (0,)), (2, (3,)), (5, (3, 3)), (0, (1,)), (-1, ())):
        with pytest.raises(WireError, match="cannot await"):
            Result(KEY, "w-1", error="boom").asking(True, (), seq=seq, awaiting=awaiting)


def test_a_request_refuses_bad_numbers() -> None:
    """Protocol 9: a request awaits earlier ones, numbered from 1 (0 is an unnumbered
    request's), ascending, at most 16; the server drops any other as malformed."""
    bad: list[dict[str, Any]] = [
        {"seq": -1},
        {"seq": 5, "awaiting": (0,)},
        {"seq": 5, "awaiting": (5,)},
        {"seq": 5, "awaiting": (3, 2)},
        {"awaiting": (1,)},
        {"seq": 20, "awaiting": tuple(range(1, 18))},
    ]
    for fields in bad:
        with pytest.raises(WireError):
            decode_request(encode_frame({"kind": "next", "worker": "w-1", **fields}, {}))


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"EVC",
        b"XXXX" + struct.pack("<I", 2) + b"{}",
        b"EVC1" + struct.pack("<I", 100) + b"{}",
        b"EVC1" + struct.pack("<I", 2) + b"[]",
        b"EVC1" + struct.pack("<I", 3) + b"\xff\xfe{",
        b"EVC1" + struct.pack("<I", 2) + b"{}",
        encode_frame({"kind": "job"}) + b"trailing",
        b"EVC1"
        + struct.pack("<I", 60)
        + b'{"arrays":[{"name":"a","dtype":"|O","shape":[1]}]}        ',
        b"EVC1" + struct.pack("<I", 50) + b'{"arrays":[{"name":"a","dtype":"<f8","shape":[9]}]}',
        b"EVC1" + struct.pack("<I", 51) + b'{"arrays":[{"name":"a","dtype":"<f8","shape":[-1]}]}',
        b"EVC1" + struct.pack("<I", 51) + b'{"arrays":[{"name":"a","dtype":["<f8"],"shape":[]}]}',
    ],
)
def test_malformed_frames_raise_wire_error(payload: bytes) -> None:
    for decode in (decode_frame, decode_job, decode_result, decode_request, decode_ack):
        with pytest.raises(WireError):
            decode(payload)


@given(st.binary(max_size=300))
@settings(max_examples=200, deadline=None)
def test_arbitrary_bytes_never_raise_anything_but_wire_error(payload: bytes) -> None:
    for decode in (decode_next_reply, decode_result, decode_results, decode_request, decode_ack):
        with contextlib.suppress(WireError):
            decode(payload)


def test_invalid_job_content_carries_its_key() -> None:
    job = make_job()
    bad = job.genomes.copy()
    bad[0, 0] = np.nan
    frame = encode_job(job).replace(job.genomes.tobytes(), bad.tobytes())
    with pytest.raises(InvalidJobError, match="NaN") as caught:
        decode_job(frame)
    assert caught.value.key == KEY
    wrong_rows = encode_frame(
        {"kind": "job", "key": KEY.model_dump(), "start": 0, "stop": 4, "lease_s": 1.0,
         "config": CONFIG.model_dump(mode="json")},
        {"genomes": np.zeros((3, W))},
    )  # fmt: skip
    with pytest.raises(InvalidJobError, match="shape"):
        decode_job(wrong_rows)
    bad_config = encode_frame(
        {"kind": "job", "key": KEY.model_dump(), "start": 0, "stop": 4, "lease_s": 1.0,
         "config": {"population": -5}},
        {"genomes": np.zeros((4, W))},
    )  # fmt: skip
    with pytest.raises(InvalidJobError) as caught:
        decode_job(bad_config)
    assert caught.value.key == KEY
    genomes = np.zeros((4, W))
    head = (  # valid JSON, a config nested deeper than orjson writes back
        b'{"kind":"job","key":{"run_id":3,"generation":7,"index":1},"start":0,"stop":4,'
        b'"lease_s":1.0,"config":' + b"[" * 300 + b"0" + b"]" * 300 + b',"arrays":[{"name":'
        b'"genomes","dtype":"<f8","shape":[4,' + str(W).encode() + b"]}]}"
    )
    deep = b"EVC1" + struct.pack("<I", len(head)) + head + genomes.tobytes()
    with pytest.raises(InvalidJobError, match="config") as caught:
        decode_job(deep)
    assert caught.value.key == KEY
    with pytest.raises(InvalidJobError, match="outside population"):
        make_job(rows=4, start=8)


def test_worker_names_are_single_key_chunks() -> None:
    assert worker_key("lab-pc.3_a") == "evocolony/workers/lab-pc.3_a"
    for bad in ("", "a/b", "a*", "x" * 129, "a b", "$"):
        with pytest.raises(ValueError):
            worker_key(bad)
        with pytest.raises(ValueError):
            JobRequest(worker=bad)


def test_results_must_be_finite_and_consistent() -> None:
    with pytest.raises(WireError, match="finite"):
        Result(KEY, "w", np.array([np.inf]))
    with pytest.raises(WireError, match="1-D"):
        Result(KEY, "w")
    with pytest.raises(WireError, match="components"):
        Result(KEY, "w", np.zeros(2), np.zeros((3, 1, 4)), start=0, stop=2)
    with pytest.raises(WireError, match="needs its slice"):
        Result(KEY, "w", np.zeros(2))
    with pytest.raises(WireError, match="does not match its slice"):
        Result(KEY, "w", np.zeros(2), start=0, stop=3)
    with pytest.raises(WireError, match="bad slice"):
        Result(KEY, "w", error="boom", start=3, stop=3)


def test_result_reply_is_an_ack_or_the_next_job_carrying_it() -> None:
    config = RunConfig(population=4, job_size=2, trials=1, steps=1)
    genomes = np.ones((2, config.network_spec.weight_count))
    key = JobKey(run_id=1, generation=0, index=0)
    ack = Ack(key=key, accepted=True)
    assert decode_result_reply(encode_message(ack)) == (ack, None)
    job = Job(JobKey(run_id=1, generation=0, index=1), 2, 4, config, genomes, lease_s=3.0)
    got_ack, got_job = decode_result_reply(encode_job(job, ack))
    assert got_ack == ack and got_job is not None
    assert got_job.key == job.key and got_job.config == config and got_job.lease_s == 3.0
    assert np.array_equal(got_job.genomes, genomes)
    bad = encode_job(job, ack).replace(b'"start":2', b'"start":9')
    with pytest.raises(InvalidJobError) as caught:
        decode_result_reply(bad)
    assert caught.value.ack == ack and caught.value.key == job.key


def span_job(span: int = 2) -> Job:
    from evorobotics.ga import GAParams, init
    from evorobotics.layout import layout

    state = init(layout(CONFIG.network_spec), GAParams.from_config(CONFIG)).to_arrays()
    genomes = np.arange(10 * W, dtype=np.float64).reshape(10, W) / 3.0
    key = JobKey(run_id=3, generation=0, index=0)
    return Job(key, 0, 10, CONFIG, genomes, span=span, state=state, more=False)


def test_span_job_round_trips_with_its_ga_state() -> None:
    job = span_job()
    back = decode_next_reply(encode_job(job))
    assert isinstance(back, Job) and back.span == 2 and back.state is not None
    assert job.state is not None and back.state.keys() == job.state.keys()
    assert all(back.state[k].tobytes() == job.state[k].tobytes() for k in job.state)
    assert back.genomes.tobytes() == job.genomes.tobytes()
    plain = decode_next_reply(encode_job(make_job()))
    assert isinstance(plain, Job) and (plain.span, plain.state) == (1, None)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"span": 3}, "passes 2"),  # generation 0 + 3 > CONFIG.generations
        ({"state": None}, "GA state"),
        ({"state": {}}, "GA state"),
        ({"start": 2, "genomes": np.zeros((8, W))}, "whole population"),
    ],
)
def test_a_span_must_fit_the_run_and_bring_its_state(
    change: dict[str, object], message: str
) -> None:
    with pytest.raises(InvalidJobError, match=message):
        replace(span_job(), **change)  # type: ignore[arg-type]


def test_a_span_frame_with_stray_arrays_is_an_invalid_job() -> None:
    job = make_job()
    frame = encode_frame(
        {
            "kind": "job",
            "key": KEY.model_dump(mode="json"),
            "start": job.start,
            "stop": job.stop,
            "lease_s": 1.0,
            "config": CONFIG.model_dump(mode="json"),
        },
        {"genomes": job.genomes, "state.generation": np.array(0)},
    )
    with pytest.raises(InvalidJobError, match="'genomes' only"):
        decode_job(frame)


def span_results(k: int, first: int = 4) -> list[Result]:
    rng = np.random.default_rng(k)
    return [
        Result(
            JobKey(run_id=3, generation=first + i, index=0),
            "w-1",
            rng.normal(size=10),
            rng.normal(size=(10, 3, 4)),
            2.5e6,
            0.01,
            start=0,
            stop=10,
            digest=genome_digest(rng.normal(size=(10, W))),
        )
        for i in range(k)
    ]


@pytest.mark.parametrize("k", [1, 5])
def test_span_results_round_trip_generation_by_generation(k: int) -> None:
    results = span_results(k)
    back = decode_results(encode_span_results(results))
    assert [r.key for r in back] == [r.key for r in results]
    for sent, got in zip(results, back, strict=True):
        assert sent.fitness is not None and got.fitness is not None
        assert sent.components is not None and got.components is not None
        assert got.fitness.tobytes() == sent.fitness.tobytes()
        assert got.components.tobytes() == sent.components.tobytes()
        assert (got.digest, got.start, got.stop, got.worker) == (sent.digest, 0, 10, "w-1")
    single = decode_results(encode_result(results[0]))
    assert len(single) == 1 and single[0].digest == results[0].digest


def test_span_results_must_be_consecutive_and_digested() -> None:
    results = span_results(3)
    with pytest.raises(ValueError, match="not generation 5"):
        encode_span_results([results[0], results[2]])
    with pytest.raises(ValueError, match="digest"):
        encode_span_results([replace(results[0], digest=None)])


def test_malformed_span_results_raise_wire_error() -> None:
    payload = encode_span_results(span_results(2))
    header, arrays = decode_frame(payload)
    broken = [
        encode_frame({**header, "digests": header["digests"][:1]}, arrays),
        encode_frame({**header, "digests": ["xyz", "abc"]}, arrays),
        encode_frame(header, {"fitness": arrays["fitness"]}),
        encode_frame(header, {**arrays, "components": arrays["components"][:, :3]}),
        encode_frame({**header, "worker": "no/slash"}, arrays),
    ]
    for bad in broken:
        with pytest.raises(WireError):
            decode_results(bad)


def test_genome_digest_sees_any_changed_bit_and_any_reordering() -> None:
    genomes = np.random.default_rng(1).normal(size=(10, W))
    changed = genomes.copy()
    changed.view(np.uint64)[3, 7] ^= 1
    assert genome_digest(genomes) == genome_digest(genomes.copy(order="F"))
    assert genome_digest(genomes) != genome_digest(changed)
    swapped = genomes[[1, 0, *range(2, 10)]]
    assert genome_digest(genomes) != genome_digest(swapped)
    assert genome_digest(genomes.astype(">f8")) == genome_digest(genomes)


TEAM_ID = "0123456789abcdef"


def test_a_team_place_round_trips_and_must_name_a_real_team() -> None:
    job = replace(span_job(), team=("lead", "helper"), member=1, team_id=TEAM_ID)
    back = decode_next_reply(encode_job(job))
    assert isinstance(back, Job)
    assert (back.team, back.member, back.team_id, back.span) == (("lead", "helper"), 1, TEAM_ID, 2)
    assert not back.shared
    shared = decode_next_reply(encode_job(replace(job, shared=True)))
    assert isinstance(shared, Job) and shared.shared and shared.team == job.team
    bad = [
        ({"span": 1, "state": None}, "needs a span"),
        ({"team": ("lead",), "member": 0}, "team of 1"),
        ({"team": tuple(f"w{i}" for i in range(11))}, "team of 11"),  # population 10
        ({"team": ("lead", "lead")}, "distinct"),
        ({"member": 2}, "member 2"),
        ({"team_id": "XYZ"}, "team id"),
        ({"team": (), "member": 0, "team_id": "", "shared": True}, "team of 0"),
    ]
    for change, message in bad:
        with pytest.raises(InvalidJobError, match=message):
            replace(job, **change)  # type: ignore[arg-type]


@given(population=st.integers(1, 500), size=st.integers(1, 64))
def test_team_cuts_cover_the_population_in_near_equal_contiguous_slices(
    population: int, size: int
) -> None:
    if size > population:
        with pytest.raises(ValueError):
            team_cuts(population, size)
        return
    cuts = team_cuts(population, size)
    widths = np.diff(cuts)
    assert cuts[0] == 0 and cuts[-1] == population and len(cuts) == size + 1
    assert widths.min() >= 1 and widths.max() - widths.min() <= 1


def test_team_messages_round_trip_and_malformed_ones_raise_wire_error() -> None:
    fitness, components = np.arange(5.0), np.ones((5, 3, 4))
    message = TeamMessage(TEAM_ID, 4, 1, ((0, 2), (6, 9)), fitness, components, "0badcafe")
    back = decode_team_message(encode_team_message(message))
    assert (back.team_id, back.generation, back.member, back.ranges) == (
        TEAM_ID,
        4,
        1,
        ((0, 2), (6, 9)),
    )
    assert back.fitness is not None and back.fitness.tobytes() == fitness.tobytes()
    assert back.components is not None and back.components.tobytes() == components.tobytes()
    assert back.digest == "0badcafe"
    over = decode_team_message(encode_team_message(TeamMessage(TEAM_ID, 4, 0, over=True)))
    assert over.over and over.fitness is None
    with pytest.raises(WireError, match="ascending"):
        TeamMessage(TEAM_ID, 4, 1, ((6, 9), (0, 2)), fitness, components, "0badcafe")
    header, arrays = decode_frame(encode_team_message(message))
    broken = [
        encode_frame({**header, "ranges": [[0, 2]]}, arrays),  # 2 individuals, 5 values
        encode_frame({**header, "ranges": [[0, 3], [2, 4]]}, arrays),  # overlapping
        encode_frame({**header, "team_id": "nope"}, arrays),
        encode_frame(header, {**arrays, "fitness": np.array([0, 1, 2, 3, np.nan])}),
        encode_frame(header, {**arrays, "components": np.ones((4, 3, 4))}),
        encode_frame(header, {**arrays, "extra": np.ones(1)}),
        encode_frame({**header, "over": True}, arrays),
        encode_frame({**header, "ranges": []}, arrays),
        encode_frame({**header, "digest": None}, arrays),  # fitness of which genomes?
        encode_frame({**header, "digest": "0BADCAFE"}, arrays),
        encode_frame({**header, "ranges": [], "digest": "0badcafe"}),  # a digest alone
    ]
    for bad in broken:
        with pytest.raises(WireError):
            decode_team_message(bad)
