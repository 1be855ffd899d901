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

The recurrence depth is one int S for every layer (layer m gets the levels 1..S whose source
exists) or a tuple of M depths, one per layer m = 1..M, so that e.g. (1, 0) feeds the hidden
layer back without the outputs' self-feedback (the paper's Fig 1B).
"""

from __future__ import annotations

import functools
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

MAX_WEIGHTS = 1_000_000
"""Upper bound on a network's weight count, so no config can exhaust memory."""


def _depths(layers: int, recurrence: int | tuple[int, ...]) -> tuple[int, ...]:
    """Depth of each layer m = 1..M; an int S is cut to the levels whose source exists."""
    if isinstance(recurrence, int):
        return tuple(min(recurrence, layers - m + 1) for m in range(1, layers + 1))
    return recurrence


@functools.lru_cache(maxsize=256)
def _weight_count(sizes: tuple[int, ...], depths: tuple[int, ...], delays: int) -> int:
    """Computed once per shape (every job's genomes are checked against it); not a cached
    property, which `model_copy(update=...)` would carry over to another shape."""
    layers = len(sizes) - 1
    per_lag = sum(
        sizes[m] * (sizes[m - 1 + s] + 1)
        for m in range(1, layers + 1)
        for s in range(depths[m - 1] + 1)
    )
    return per_lag * (delays + 1)


class NetworkSpec(BaseModel):
    """Layer sizes, output activation, time-delay depth T and recurrence depth(s) S."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    inputs: int = Field(5, ge=1, le=64, description="input neurons (five binary whiskers)")
    hidden: tuple[int, ...] = Field(
        (9,), max_length=8, description="hidden layer sizes, input side first; () for none"
    )
    outputs: int = Field(2, ge=1, le=64, description="output neurons (left, right wheel)")
    output_activation: Literal["sigmoid", "linear"] = "sigmoid"
    delays: int = Field(2, ge=0, le=32, description="time-delay depth T: lags 0..T")
    recurrence: int | tuple[int, ...] = Field(
        0,
        description="recurrence depth S: feedback levels 1..S for every layer, or one depth per "
        "layer m = 1..M (input side first, outputs last)",
    )

    @model_validator(mode="after")
    def _check_shape(self) -> NetworkSpec:
        for k, size in enumerate(self.hidden, start=1):
            if not 1 <= size <= 1024:
                raise ValueError(f"hidden layer {k} has {size} neurons; allowed 1..1024")
        self._check_recurrence()
        count = self.weight_count
        if count > MAX_WEIGHTS:
            raise ValueError(f"network has {count} weights; the limit is {MAX_WEIGHTS}")
        return self

    def _check_recurrence(self) -> None:
        rec, layers = self.recurrence, self.layers
        if isinstance(rec, int):
            if not 0 <= rec <= layers:
                raise ValueError(
                    f"recurrence depth {rec} is outside 0..{layers}, the layers of this "
                    f"network: level s feeds layer m from layer m-1+s, which must exist"
                )
            return
        if len(rec) != layers:
            raise ValueError(
                f"recurrence has {len(rec)} depth(s) but the network has {layers} layer(s): "
                f"give one per layer m = 1..{layers}, input side first"
            )
        for m, depth in enumerate(rec, start=1):
            if not 0 <= depth <= layers - m + 1:
                raise ValueError(
                    f"recurrence depth {depth} of layer {m} is outside 0..{layers - m + 1}: "
                    f"level s feeds layer m from layer m-1+s, which must exist"
                )

    @property
    def layers(self) -> int:
        """M: hidden layers plus the output layer."""
        return len(self.hidden) + 1

    @property
    def sizes(self) -> tuple[int, ...]:
        """Neuron count of layers 0 (inputs) .. M (outputs)."""
        return (self.inputs, *self.hidden, self.outputs)

    def recurrence_of(self, m: int) -> int:
        """Recurrence depth of layer m = 1..M: its levels are s = 0..depth."""
        if not 1 <= m <= self.layers:
            raise ValueError(f"layer {m} is outside 1..{self.layers}")
        return _depths(self.layers, self.recurrence)[m - 1]

    def source(self, m: int, s: int) -> int | None:
        """Layer feeding layer m at source level s, or None where layer m has no level s."""
        return m - 1 + s if 0 <= s <= self.recurrence_of(m) else None

    @property
    def weight_count(self) -> int:
        """Length of the chromosome: every sub-matrix W[m,t,s] with its bias column."""
        return _weight_count(self.sizes, _depths(self.layers, self.recurrence), self.delays)


PRESETS: dict[str, NetworkSpec] = {
    # Fig 5: one hidden layer, time-delayed; 3 x (9*6 + 2*10) = 222 weights (paper: 220).
    "paper-best": NetworkSpec(hidden=(9,), delays=2, recurrence=0),
    # Section 4: three hidden layers, recurrent, eight delay taps; 7104 weights (paper: ~7000).
    "paper-largest": NetworkSpec(hidden=(10, 10, 10), delays=7, recurrence=2),
    # A purely reactive baseline of about the paper-best size: 8*27 + 2 = 218 weights.
    "reactive": NetworkSpec(hidden=(27,), delays=0, recurrence=0),
    # A small Elman/Jordan network: self and output feedback, one delay; 232 weights.
    "recurrent-small": NetworkSpec(hidden=(6,), delays=1, recurrence=2),
    # Fig 1B: two hidden layers, time-delayed, hidden-layer self-feedback only; 396 weights.
    "fig1b": NetworkSpec(hidden=(5, 5), delays=2, recurrence=(1, 1, 0)),
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
