"""Framing and checksum of the BasicX serial protocol (docs/serial-protocol.md)."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from robot_agent.serial_protocol import (
    MAX_LINE,
    UNKNOWN_SEQ,
    Frame,
    FrameError,
    LineDecoder,
    checksum,
    decode_line,
    encode,
    motor_units,
    parse_whisker_bits,
    whisker_bits,
)

seqs = st.one_of(st.integers(0, 255), st.just(UNKNOWN_SEQ))
bodies = st.text(
    alphabet=st.characters(min_codepoint=0x20, max_codepoint=0x7E, exclude_characters="$*"),
    max_size=MAX_LINE - 10,
)
frames = st.builds(Frame, seqs, bodies)
noise = st.binary(max_size=300).map(lambda b: b.replace(b"$", b""))


def test_known_frame_bytes() -> None:
    # checksum over "01 V": 0x30 ^ 0x31 ^ 0x20 ^ 0x56 = 0x77
    assert encode(1, "V") == b"$01 V*77\n"
    assert decode_line(b"$01 V*77") == Frame(1, "V")
    assert decode_line(b"$01 V*77\r") == Frame(1, "V")
    assert encode(UNKNOWN_SEQ, "ERR CK").startswith(b"$-- ERR CK*")


@given(frames)
def test_round_trip(frame: Frame) -> None:
    line = encode(frame.seq, frame.body)
    assert line.endswith(b"\n") and len(line) <= MAX_LINE
    assert decode_line(line[:-1]) == frame


@given(frames, st.data())
def test_any_single_byte_change_is_caught(frame: Frame, data: st.DataObject) -> None:
    line = bytearray(encode(frame.seq, frame.body)[:-1])
    pos = data.draw(st.integers(0, len(line) - 1))
    new = data.draw(st.integers(0, 255).filter(lambda b: b not in (line[pos], ord("$"), 10)))
    line[pos] = new
    with pytest.raises(FrameError):
        decode_line(bytes(line))


def test_checksum_failure_is_told_apart_from_noise() -> None:
    good = encode(7, "W 10101")[:-1]
    with pytest.raises(FrameError) as bad_ck:
        decode_line(good[:-1] + (b"0" if good[-1:] != b"0" else b"1"))
    assert bad_ck.value.checksum_failed
    with pytest.raises(FrameError) as noise_err:
        decode_line(b"\x00\xffhello")
    assert not noise_err.value.checksum_failed


@given(st.lists(st.tuples(noise, frames), max_size=6), st.lists(st.integers(1, 40), min_size=1))
def test_decoder_resynchronises_after_noise_under_any_chunking(
    pairs: list[tuple[bytes, Frame]], cuts: list[int]
) -> None:
    stream = b"".join(n + encode(f.seq, f.body) for n, f in pairs)
    decoder = LineDecoder()
    decoded: list[Frame | FrameError] = []
    pos, k = 0, 0
    while pos < len(stream):
        size = cuts[k % len(cuts)]
        decoded += decoder.feed(stream[pos : pos + size])
        pos, k = pos + size, k + 1
    assert [d for d in decoded if isinstance(d, Frame)] == [f for _, f in pairs]


def test_decoder_bounds_its_buffer() -> None:
    decoder = LineDecoder()
    assert decoder.feed(b"x" * 10_000) == []
    assert len(decoder._buffer) <= MAX_LINE
    assert decoder.feed(encode(3, "OK")) == [Frame(3, "OK")]


def test_encode_rejects_bad_arguments() -> None:
    for seq, body in (
        (256, "OK"),
        (-2, "OK"),
        (1, "a*b"),
        (1, "a$b"),
        (1, "tab\t"),
        (1, "x" * 200),
    ):
        with pytest.raises(ValueError):
            encode(seq, body)


def test_checksum_is_xor() -> None:
    assert checksum(b"") == 0
    assert checksum(b"\x0f\xf0") == 0xFF


@given(st.floats(allow_nan=False))
def test_motor_units_clamp(value: float) -> None:
    units = motor_units(value)
    assert -1000 <= units <= 1000
    if -1 <= value <= 1:
        assert abs(units / 1000 - value) <= 0.0005 + 1e-9


def test_motor_units_rejects_nan() -> None:
    with pytest.raises(ValueError):
        motor_units(float("nan"))


@given(st.tuples(*[st.booleans()] * 5))
def test_whisker_bits_round_trip(bits: tuple[bool, ...]) -> None:
    assert parse_whisker_bits(whisker_bits(bits)) == bits


def test_whisker_bits_reject_bad_text() -> None:
    for text in ("0101", "010101", "0102x"):
        with pytest.raises(ValueError):
            parse_whisker_bits(text)
