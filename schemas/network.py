"""The controller network's shape (paper section 2.1, Eqs 1-6), as a validated config.

A `NetworkSpec` fixes the layered structure before evolution; only weights evolve. Indices
follow the paper with two documented shifts (see docs/science.md):

- layers m = 1..M, where M = len(hidden) + 1 and layer M is the output layer; layer 0 is the
  input vector (the five whiskers);
- delay lag t = 0..T (the paper's t = lag + 1): a connection with lag t reads its source t
  steps further back;
- source level s = 0..S (the paper's s = level + 1): s = 0 is the feed-forward source, layer
  m - 1 at this step; s >= 1 is recurrent, layer m - 1 + s at the previous step (s = 1 is the
  layer itself, Elman-style; s = 2 the next deeper layer, Jordan-style for m = M - 1).
"""

from __future__ import annotations

import functools
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

MAX_WEIGHTS = 1_000_000
"""Upper bound on a network's weight count, so no config can exhaust memory."""


def _source(layers: int, m: int, s: int) -> int | None:
    src = m - 1 + s
    return src if src <= layers else None


@functools.lru_cache(maxsize=256)
def _weight_count(sizes: tuple[int, ...], recurrence: int, delays: int) -> int:
    """Computed once per shape (every job's genomes are checked against it); not a cached
    property, which `model_copy(update=...)` would carry over to another shape."""
    layers = len(sizes) - 1
    per_lag = 0
    for m in range(1, layers + 1):
        for s in range(recurrence + 1):
            src = _source(layers, m, s)
            if src is not None:
                per_lag += sizes[m] * (sizes[src] + 1)
    return per_lag * (delays + 1)


class NetworkSpec(BaseModel):
    """Layer sizes, output activation, time-delay depth T and recurrence depth S."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    inputs: int = Field(5, ge=1, le=64, description="input neurons (five binary whiskers)")
    hidden: tuple[int, ...] = Field(
        (9,), max_length=8, description="hidden layer sizes, input side first; () for none"
    )
    outputs: int = Field(2, ge=1, le=64, description="output neurons (left, right wheel)")
    output_activation: Literal["sigmoid", "linear"] = "sigmoid"
    delays: int = Field(2, ge=0, le=32, description="time-delay depth T: lags 0..T")
    recurrence: int = Field(0, ge=0, description="recurrence depth S: feedback levels 1..S")

    @model_validator(mode="after")
    def _check_shape(self) -> NetworkSpec:
        for k, size in enumerate(self.hidden, start=1):
            if not 1 <= size <= 1024:
                raise ValueError(f"hidden layer {k} has {size} neurons; allowed 1..1024")
        if self.recurrence > self.layers:
            raise ValueError(
                f"recurrence depth {self.recurrence} exceeds the {self.layers} layer(s) of this "
                f"network: level s feeds layer m from layer m-1+s, which must exist"
            )
        count = self.weight_count
        if count > MAX_WEIGHTS:
            raise ValueError(f"network has {count} weights; the limit is {MAX_WEIGHTS}")
        return self

    @property
    def layers(self) -> int:
        """M: hidden layers plus the output layer."""
        return len(self.hidden) + 1

    @property
    def sizes(self) -> tuple[int, ...]:
        """Neuron count of layers 0 (inputs) .. M (outputs)."""
        return (self.inputs, *self.hidden, self.outputs)

    def source(self, m: int, s: int) -> int | None:
        """Layer feeding layer m at source level s, or None where it does not exist."""
        return _source(self.layers, m, s)

    @property
    def weight_count(self) -> int:
        """Length of the chromosome: every sub-matrix W[m,t,s] with its bias column."""
        return _weight_count(self.sizes, self.recurrence, self.delays)


PRESETS: dict[str, NetworkSpec] = {
    # Fig 5: one hidden layer, time-delayed; 3 x (9*6 + 2*10) = 222 weights (paper: 220).
    "paper-best": NetworkSpec(hidden=(9,), delays=2, recurrence=0),
    # Section 4: three hidden layers, recurrent, eight delay taps; 7104 weights (paper: ~7000).
    "paper-largest": NetworkSpec(hidden=(10, 10, 10), delays=7, recurrence=2),
    # A purely reactive baseline of about the paper-best size: 8*27 + 2 = 218 weights.
    "reactive": NetworkSpec(hidden=(27,), delays=0, recurrence=0),
    # A small Elman/Jordan network: self and output feedback, one delay; 232 weights.
    "recurrent-small": NetworkSpec(hidden=(6,), delays=1, recurrence=2),
}
"""Named networks; `docs/science.md` lists their exact weight counts (tests check them)."""


def resolve_network(name: str) -> NetworkSpec:
    """A preset by name; ValueError listing the presets otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown network preset {name!r}; choose one of {sorted(PRESETS)} or give a JSON file"
        ) from None
