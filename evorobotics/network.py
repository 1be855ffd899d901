"""The controller network (paper Eqs 1-6, 8): one step of a batch of controllers, state explicit.

Semantics. Layers m = 1..M (M = len(hidden) + 1, layer M the outputs); layer 0 is the input
vector. At step k, a_0(k) = inputs, then for m = 1..M in order

    u_m = sum over the blocks W[m,t,s] of layer m of  W[m,t,s] @ [x; 1]   (Eq 3: bias last)
        s = 0:  x = a_{m-1}(k - t)        (t = 0 is this step's value, just computed)
        s >= 1: x = a_{m-1+s}(k - 1 - t)  (recurrent: the previous step and earlier)
    a_m(k) = sigmoid(u_m), or sat(u_m) for a linear output layer (Eqs 1-2).

sat(u) = clip(u, -LINEAR_BOUND, LINEAR_BOUND), and 0 for NaN: a linear output fed back with a
gain above 1 grows geometrically and would reach inf, then NaN, within a few hundred steps.
LINEAR_BOUND = 1e6 is far beyond anything a non-diverging controller produces (the wheels
saturate at |y| = 1), so results where no output reaches it are bit-identical to the unbounded
Eq 2, and small enough that no weighted sum of bounded activations overflows.

Before the first step every past activation and input is 0, so a zero weight is exactly an
absent connection.

State layout. The state of one controller is a float64 row of `state_size(spec)` values:
layer j = 0..M in order, each as T+1 slots of n_j values, most recent first. After step k,
slot r of layer j holds a_j(k - r), at `hist_off[j] + r * n_j`. Hence state_size =
(T+1) * sum(n_j). A step reads slot t-1 for feed-forward lags t >= 1 and slot t for recurrent
lags, then shifts every layer's slots by one and writes this step's activations to slot 0.

Kernel call convention (for fused numba kernels, e.g. the simulator's episode loop). With
`plan = kernel_plan(spec)` (a `KernelPlan`, fields in this order):

    step_one(w, plan.sizes, plan.hist_off, plan.act_off, plan.blocks, plan.delays,
             plan.linear_output, state_row, inputs_row, out_row, scratch)

  w           float64[:]  (n_weights,)  one chromosome (Layout order m, t, s, neuron, input)
  sizes       int64[:]    (M+1,)        neurons of layers 0..M
  hist_off    int64[:]    (M+1,)        offset of layer j's history in a state row
  act_off     int64[:]    (M+1,)        offset of layer j's new activations in scratch
  blocks      int64[:, :] (n_blocks, 5) rows (m, t, s, src, offset) in chromosome order
  delays      int                       T
  linear_output int                     1 for linear outputs, 0 for sigmoid
  state_row   float64[:]  (state_size,) advanced in place
  inputs_row  float64[:]  (inputs,)     read only
  out_row     float64[:]  (outputs,)    receives the raw outputs a_M(k)
  scratch     float64[:]  (scratch_size,) work space, contents irrelevant between calls

It allocates nothing. From Python, `step_one(w, *plan, state_row, inputs_row, out_row,
scratch)` is the same call. `motor_one(out_row, linear_output, motor_row)` is the compiled
twin of `motor_commands` for one robot: finite commands in [-1, 1] whatever the outputs (NaN
gives 0).

Specialised tile kernels. `spec_kernel(spec)` is `step_one` with the plan baked in, for a tile
of LANES = 8 controllers at once: Python source generated per spec (constant loop bounds, block
offsets and state offsets, blocks summed in the same order), written as a real module file in
the kernel cache directory (`cached_module`) and compiled with `njit(cache=True)`, so the
compile is paid once per machine, not per process. Its call is
`kernel(w, state, inputs, out, scratch, live)` on (rows, LANES) arrays, one controller per
column; each neuron's sums and sigmoid are SIMD over the lanes, several neurons' interleaved
(`_accumulate_rows`, `_sigmoid_rows`), and every live lane is bit-identical to `step_one`
(same operations in the same order, no fastmath; the exp is the fixed polynomial `_exp_neg`
in both; tested).

`step` is a compiled loop over tiles of the batch calling `spec_kernel(spec)`, and the
simulator's fused episode kernel calls the same function: one compiled path, so a controller's
outputs are bit-identical whatever the batch size, its lane, and wherever it runs (robot or
simulation).
`step_reference` is an independent vectorised numpy version used by the tests.
"""

from __future__ import annotations

import hashlib
import importlib.util
import itertools
import math
import os
import pickle
import stat
import sys
import tempfile
import threading
from collections.abc import Callable, Sequence
from functools import cache
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple, cast

import numba
import numpy as np
from llvmlite import ir as llvm_ir
from numba import njit, types
from numba.core import cgutils
from numba.core.typing.templates import Signature
from numba.extending import intrinsic

from evorobotics.layout import layout
from schemas.network import NetworkSpec


def _import_numba_arrays() -> None:
    """Import numba's array implementations (`numba.np.arraymath`) before a kernel loads them,
    with scipy.linalg hidden from the BLAS probe that module runs at import: importing
    scipy.linalg costs 0.15-0.3 s of every process's start (it clones numpy's namespace, f2py
    and unittest included), and no kernel here calls BLAS. Numba then takes its own loop for
    the inner products of np.correlate and np.convolve, and still imports scipy.linalg when
    compiled code calls np.dot or np.linalg."""
    probed = "scipy.linalg.cython_blas"
    if "numba.np.arraymath" in sys.modules or probed in sys.modules:
        return
    sys.modules[probed] = None  # type: ignore[assignment]  # its import raises ImportError
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules[probed]


_import_numba_arrays()


class KernelPlan(NamedTuple):
    """Everything `step_one` needs about a spec, as numba-friendly arrays and ints."""

    sizes: np.ndarray
    """int64 (M+1,): neurons of layers 0..M."""
    hist_off: np.ndarray
    """int64 (M+1,): where layer j's T+1 history slots start in a state row."""
    act_off: np.ndarray
    """int64 (M+1,): where layer j's activations of this step start in scratch."""
    blocks: np.ndarray
    """int64 (n_blocks, 5): (m, t, s, src, offset) of each W[m,t,s], chromosome order."""
    delays: int
    """T: the deepest delay lag."""
    linear_output: int
    """1 if the output layer is linear (Eq 2), 0 if sigmoid (Eq 1)."""


@cache
def kernel_plan(spec: NetworkSpec) -> KernelPlan:
    """The plan of `spec` (cached; arrays are read-only because they are shared)."""
    sizes = np.array(spec.sizes, dtype=np.int64)
    act_off = np.concatenate(([0], np.cumsum(sizes)[:-1])).astype(np.int64)
    hist_off = act_off * (spec.delays + 1)
    blocks = np.array(
        [(b.m, b.t, b.s, b.src, b.offset) for b in layout(spec).blocks], dtype=np.int64
    ).reshape(-1, 5)
    for arr in (sizes, act_off, hist_off, blocks):
        arr.flags.writeable = False
    return KernelPlan(
        sizes, hist_off, act_off, blocks, spec.delays, int(spec.output_activation == "linear")
    )


def state_size(spec: NetworkSpec) -> int:
    """Length of one controller's state row: T+1 history slots of every layer 0..M."""
    return (spec.delays + 1) * sum(spec.sizes)


def scratch_size(spec: NetworkSpec) -> int:
    """Length of the work array `step_one` needs: this step's activations of layers 0..M."""
    return sum(spec.sizes)


def reset(spec: NetworkSpec, batch: int) -> np.ndarray:
    """The state of `batch` controllers before their first step: every past value is 0."""
    if batch < 0:
        raise ValueError(f"batch must be >= 0, got {batch}")
    return np.zeros((batch, state_size(spec)), dtype=np.float64)


LINEAR_BOUND = 1e6
"""|a_M| of a linear output layer never exceeds this (see the module docstring)."""


@njit(cache=True)
def _saturate(u: float) -> float:
    # A linear output: clipped to +-LINEAR_BOUND, NaN to 0; the same as `_saturate_array`.
    if math.isnan(u):
        return 0.0
    if u > LINEAR_BOUND:
        return LINEAR_BOUND
    if u < -LINEAR_BOUND:
        return -LINEAR_BOUND
    return u


EXP_FLOOR = -708.0
"""exp of anything below this is taken as 0 (exp(-708) is still a normal double)."""
LOG2E = 1.4426950408889634
LN2_HI = 0.6931467056274414
"""ln 2 to 21 bits: k * LN2_HI is exact for every k of the range reduction."""
LN2_LO = 4.7493250390316726e-07
"""ln 2 - LN2_HI."""
EXP_TAYLOR = tuple(1.0 / math.factorial(i) for i in range(13, -1, -1))
"""Taylor coefficients of e^r, highest degree first (Horner order): degree 13 leaves a
truncation error below 1e-17 for |r| <= ln 2 / 2."""


@njit(cache=True)
def _exp_neg(x: float) -> float:
    """e^x for x <= 0 (and NaN), in operations `_sigmoid_rows` repeats lane by lane.

    Not libm's exp (whose SIMD and scalar versions round differently) but one fixed sequence
    of IEEE operations: x = k ln 2 + r, |r| <= ln 2 / 2, e^r by Horner, times 2^k exactly. Within
    a few ulp of exp; identical bits scalar or vectorised, on any machine.
    """
    if not x > EXP_FLOOR:
        return x if math.isnan(x) else 0.0
    k = math.floor(x * LOG2E + 0.5)
    r = (x - k * LN2_HI) - k * LN2_LO
    p = EXP_TAYLOR[0]
    for i in range(1, len(EXP_TAYLOR)):
        p = p * r + EXP_TAYLOR[i]
    return p * math.ldexp(1.0, int(k))


@njit(cache=True)
def _sigmoid(u: float) -> float:
    # Written so exp never overflows: the formula of `_sigmoid_array`, with `_exp_neg` for exp.
    e = _exp_neg(-abs(u))
    if u >= 0.0:
        return 1.0 / (1.0 + e)
    return e / (1.0 + e)


@njit(cache=True)
def _accumulate(
    w: np.ndarray,
    off: int,
    rows: int,
    n_src: int,
    x: np.ndarray,
    x_off: int,
    u: np.ndarray,
    u_off: int,
) -> None:
    # u[u_off + n] += sum_i W[n, i] x[x_off + i] + W[n, bias]; fixed order, no reassociation.
    cols = n_src + 1
    for n in range(rows):
        row = off + n * cols
        acc = 0.0
        for i in range(n_src):
            acc += w[row + i] * x[x_off + i]
        acc += w[row + n_src]
        u[u_off + n] += acc


LANES = 8
"""Controllers a tile kernel steps at once: one per lane, lanes side by side in memory (structure
of arrays: a row of LANES float64 per weight, state value or activation), so each multiply-add
of a tile is one SIMD instruction."""


def _literal(value: types.Type) -> int | None:
    """The value of a compile-time integer argument of an intrinsic, None if not a literal."""
    return value.literal_value if isinstance(value, types.IntegerLiteral) else None


@intrinsic
def _accumulate_rows(
    typingctx: object,
    w: types.Array,
    row: types.Integer,
    rows: types.IntegerLiteral,
    n_src: types.Integer,
    x: types.Array,
    x_row: types.Integer,
    u: types.Array,
    u_row: types.Integer,
) -> tuple[Signature, Callable[..., object]] | None:
    """`_accumulate` of `rows` neurons for the LANES lanes of (rows, LANES) C arrays, as SIMD.

    For neuron k < rows, whose weights start at w[row + k (n_src + 1)]: u[u_row + k] +=
    (sum_i w x[x_row + i]) + bias, lane by lane: acc = 0, += w x input by input, += bias,
    u += acc, the order of `step_one`, so every lane gets its bits. The neurons' sums are
    independent chains of additions: each input's step is issued for every neuron in turn (a
    loop over the inputs, `rows`, a literal, accumulators in it), so they overlap instead of
    waiting on one another. Written in LLVM vector instructions because numba's defaults (no
    SLP vectoriser, small loops unrolled before the loop vectoriser) leave a lane loop scalar.
    """
    count = _literal(rows)
    if count is None:
        return None
    sig = types.void(w, row, rows, n_src, x, x_row, u, u_row)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> object:
        w_a, row_v, _, n_v, x_a, xr_v, u_a, ur_v = args
        tys = signature.args
        row_v, n_v, xr_v, ur_v = (
            context.cast(builder, v, t, types.intp)
            for v, t in ((row_v, tys[1]), (n_v, tys[3]), (xr_v, tys[5]), (ur_v, tys[7]))
        )
        vec = llvm_ir.VectorType(llvm_ir.DoubleType(), LANES)
        stride = builder.add(n_v, llvm_ir.Constant(n_v.type, 1))  # a neuron's weights

        def at(ty: types.Array, value: object, index: object) -> object:
            data = context.make_array(ty)(context, builder, value).data
            offset = builder.mul(index, llvm_ir.Constant(index.type, LANES))  # type: ignore[attr-defined]
            return builder.bitcast(builder.gep(data, [offset]), vec.as_pointer())

        def weight(k: int, i: object) -> object:
            first = builder.add(row_v, builder.mul(stride, llvm_ir.Constant(stride.type, k)))
            return builder.load(at(tys[0], w_a, builder.add(first, i)), align=8)

        zero = llvm_ir.Constant(vec, [0.0] * LANES)
        accs = [cgutils.alloca_once_value(builder, zero) for _ in range(count)]  # type: ignore[no-untyped-call]
        with cgutils.for_range(builder, n_v) as loop:
            xi = builder.load(at(tys[4], x_a, builder.add(xr_v, loop.index)), align=8)
            for k, acc in enumerate(accs):
                term = builder.fmul(weight(k, loop.index), xi)
                builder.store(builder.fadd(builder.load(acc), term), acc)
        for k, acc in enumerate(accs):
            target = at(tys[6], u_a, builder.add(ur_v, llvm_ir.Constant(ur_v.type, k)))
            total = builder.fadd(builder.load(acc), weight(k, n_v))
            builder.store(builder.fadd(builder.load(target, align=8), total), target, align=8)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _copy_tile(
    typingctx: object,
    dst: types.Array,
    dst_row: types.Integer,
    src: types.Array,
    src_row: types.Integer,
    rows: types.Integer,
) -> tuple[Signature, Callable[..., object]]:
    """dst[dst_row + i] = src[src_row + i] for i < rows, whole LANES-wide rows as SIMD moves
    (a lane loop would be unrolled into scalar moves). Ranges must not overlap."""
    sig = types.void(dst, dst_row, src, src_row, rows)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> object:
        tys = signature.args
        dst_v, src_v = args[0], args[2]
        dr, sr, n = (context.cast(builder, args[k], tys[k], types.intp) for k in (1, 3, 4))
        vec = llvm_ir.VectorType(llvm_ir.DoubleType(), LANES)
        lanes = llvm_ir.Constant(dr.type, LANES)

        def at(ty: types.Array, value: object, r: object) -> object:
            data = context.make_array(ty)(context, builder, value).data
            return builder.bitcast(builder.gep(data, [builder.mul(r, lanes)]), vec.as_pointer())

        with cgutils.for_range(builder, n) as loop:
            row = builder.load(at(tys[2], src_v, builder.add(sr, loop.index)), align=8)
            builder.store(row, at(tys[0], dst_v, builder.add(dr, loop.index)), align=8)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _sigmoid_rows(
    typingctx: object,
    a: types.Array,
    row: types.Integer,
    rows: types.IntegerLiteral,
    live: types.Array,
) -> tuple[Signature, Callable[..., object]] | None:
    """a[row + k] = `_sigmoid`(a[row + k]) for k < rows (a literal) in the live lanes of a
    (rows, LANES) C array, as SIMD.

    The operations of `_sigmoid` and `_exp_neg` lane by lane (2^k built from its exponent
    bits rather than by ldexp: the same exact power of two), so every lane gets their bits.
    Each operation is issued for every row in turn: the rows' exp chains overlap instead of
    waiting on one another. An idle lane (live[lane] == 0) keeps its value.
    """
    count = _literal(rows)
    if count is None:
        return None
    sig = types.void(a, row, rows, live)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> object:
        a_v, row_v, _, live_v = args
        row_v = context.cast(builder, row_v, signature.args[1], types.intp)
        f64 = llvm_ir.DoubleType()
        i64 = llvm_ir.IntType(64)
        vec = llvm_ir.VectorType(f64, LANES)
        ivec = llvm_ir.VectorType(i64, LANES)

        def splat(value: float) -> object:
            return llvm_ir.Constant(vec, [value] * LANES)

        def call(name: str, *operands: object) -> object:
            fnty = llvm_ir.FunctionType(vec, [vec] * len(operands))
            fn = cgutils.get_or_insert_function(  # type: ignore[no-untyped-call]
                builder.module, fnty, f"llvm.{name}.v8f64"
            )
            return builder.call(fn, operands)

        def each(op: Callable[..., object], *values: list[object]) -> list[object]:
            return [op(*operands) for operands in zip(*values, strict=True)]

        data = context.make_array(signature.args[0])(context, builder, a_v).data
        ptrs = [
            builder.bitcast(
                builder.gep(
                    data,
                    [
                        builder.mul(
                            builder.add(row_v, llvm_ir.Constant(row_v.type, k)),
                            llvm_ir.Constant(row_v.type, LANES),
                        )
                    ],
                ),
                vec.as_pointer(),
            )
            for k in range(count)
        ]
        u = [builder.load(ptr, align=8) for ptr in ptrs]
        x = each(lambda v: builder.fneg(call("fabs", v)), u)
        inside = each(lambda v: builder.fcmp_ordered(">", v, splat(EXP_FLOOR)), x)
        # NaN lanes too: no poison below
        xc = each(lambda c, v: builder.select(c, v, splat(EXP_FLOOR)), inside, x)
        k = each(
            lambda v: call("floor", builder.fadd(builder.fmul(v, splat(LOG2E)), splat(0.5))), xc
        )
        r = each(
            lambda v, n: builder.fsub(
                builder.fsub(v, builder.fmul(n, splat(LN2_HI))), builder.fmul(n, splat(LN2_LO))
            ),
            xc,
            k,
        )
        p = [splat(EXP_TAYLOR[0])] * count
        for coefficient in EXP_TAYLOR[1:]:
            term = splat(coefficient)
            p = each(lambda q, v, c=term: builder.fadd(builder.fmul(q, v), c), p, r)
        bits = each(
            lambda n: builder.shl(
                builder.add(builder.fptosi(n, ivec), llvm_ir.Constant(ivec, [1023] * LANES)),
                llvm_ir.Constant(ivec, [52] * LANES),
            ),
            k,
        )
        e = each(lambda q, b: builder.fmul(q, builder.bitcast(b, vec)), p, bits)
        e = each(
            lambda c, v, ev: builder.select(
                c, ev, builder.select(builder.fcmp_unordered("uno", v, v), v, splat(0.0))
            ),
            inside,
            x,
            e,
        )
        # one division: select the numerator (the same operands, so the same bits)
        y = each(
            lambda v, ev: builder.fdiv(
                builder.select(builder.fcmp_ordered(">=", v, splat(0.0)), splat(1.0), ev),
                builder.fadd(splat(1.0), ev),
            ),
            u,
            e,
        )
        live_data = context.make_array(signature.args[3])(context, builder, live_v).data
        mask = builder.load(
            builder.bitcast(
                live_data, llvm_ir.VectorType(live_data.type.pointee, LANES).as_pointer()
            ),
            align=1,
        )
        on = builder.icmp_unsigned("!=", mask, llvm_ir.Constant(mask.type, [0] * LANES))
        for ptr, v, out in zip(ptrs, u, y, strict=True):
            builder.store(builder.select(on, out, v), ptr, align=8)
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True)
def step_one(
    w: np.ndarray,
    sizes: np.ndarray,
    hist_off: np.ndarray,
    act_off: np.ndarray,
    blocks: np.ndarray,
    delays: int,
    linear_output: int,
    state_row: np.ndarray,
    inputs_row: np.ndarray,
    out_row: np.ndarray,
    scratch: np.ndarray,
) -> None:
    """Advance one controller by one step in place (see the module docstring)."""
    top = sizes.shape[0] - 1
    for i in range(sizes[0]):
        scratch[act_off[0] + i] = inputs_row[i]
    b = 0
    n_blocks = blocks.shape[0]
    for m in range(1, top + 1):
        rows = sizes[m]
        base = act_off[m]
        for n in range(rows):
            scratch[base + n] = 0.0
        while b < n_blocks and blocks[b, 0] == m:
            t = blocks[b, 1]
            s = blocks[b, 2]
            src = blocks[b, 3]
            off = blocks[b, 4]
            n_src = sizes[src]
            if s == 0 and t == 0:
                _accumulate(w, off, rows, n_src, scratch, act_off[src], scratch, base)
            elif s == 0:
                x_off = hist_off[src] + (t - 1) * n_src
                _accumulate(w, off, rows, n_src, state_row, x_off, scratch, base)
            else:
                x_off = hist_off[src] + t * n_src
                _accumulate(w, off, rows, n_src, state_row, x_off, scratch, base)
            b += 1
        if m < top or linear_output == 0:
            for n in range(rows):
                scratch[base + n] = _sigmoid(scratch[base + n])
        else:
            for n in range(rows):
                scratch[base + n] = _saturate(scratch[base + n])
    for j in range(top + 1):
        n_j = sizes[j]
        h = hist_off[j]
        for r in range(delays, 0, -1):
            for i in range(n_j):
                state_row[h + r * n_j + i] = state_row[h + (r - 1) * n_j + i]
        for i in range(n_j):
            state_row[h + i] = scratch[act_off[j] + i]
    for i in range(sizes[top]):
        out_row[i] = scratch[act_off[top] + i]


Kernel = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], None]
"""A specialised step of a tile: kernel(w, state, inputs, out, scratch, live), see `spec_kernel`."""


INTERLEAVE = 8
"""Most neurons whose sums or sigmoids a kernel interleaves (`_accumulate_rows`,
`_sigmoid_rows`): enough independent chains to fill the pipelines, few enough to stay in
registers."""


def _groups(rows: int) -> list[tuple[int, int]]:
    """(first, count) of a layer's neurons in near-equal groups of at most INTERLEAVE."""
    n = -(-rows // INTERLEAVE)
    bounds = [rows * i // n for i in range(n + 1)]
    return [(a, b - a) for a, b in itertools.pairwise(bounds)]


def _kernel_source(spec: NetworkSpec) -> str:
    """Module source of `kernel` (one step of a tile of LANES controllers) and `batch` for `spec`.

    Per lane and neuron the sums are those of `step_one` in the same order (u = 0, then per
    block in chromosome order acc = 0, += w x input by input, += bias, u += acc), so every lane
    is bit-identical to `step_one`; `_accumulate_rows` does a group of neurons' sums for the
    whole tile in SIMD instructions, `_sigmoid_rows` their sigmoids.
    """
    plan = kernel_plan(spec)
    sizes = [int(v) for v in plan.sizes]
    hist = [int(v) for v in plan.hist_off]
    act = [int(v) for v in plan.act_off]
    top = len(sizes) - 1
    lines = [
        f'"""Generated by evorobotics.network for {spec!r}; do not edit."""',
        "",
        "import numpy as np",
        "from numba import njit",
        "",
        "from evorobotics.network import _accumulate_rows, _copy_tile, _saturate, _sigmoid_rows",
        "",
        "",
        "@njit(cache=True)",
        "def kernel(w, state, x, out, scratch, live):",
        f"    _copy_tile(scratch, 0, x, 0, {sizes[0]})",
    ]
    for m in range(1, top + 1):
        lines += [
            f"    for n in range({sizes[m]}):",
            f"        for lane in range({LANES}):",
            f"            scratch[{act[m]} + n, lane] = 0.0",
        ]
        groups = _groups(sizes[m])
        for m_b, t, s, src, offset in plan.blocks.tolist():
            if m_b != m:
                continue
            n_src = sizes[src]
            if s == 0 and t == 0:
                x = f"scratch, {act[src]}"
            elif s == 0:
                x = f"state, {hist[src] + (t - 1) * n_src}"
            else:
                x = f"state, {hist[src] + t * n_src}"
            for first, rows in groups:
                row = offset + first * (n_src + 1)
                lines.append(
                    f"    _accumulate_rows(w, {row}, {rows}, {n_src}, {x}, scratch, "
                    f"{act[m] + first})"
                )
        if m == top and plan.linear_output == 1:
            lines += [  # an idle lane (zero weights and inputs) keeps u = 0
                f"    for n in range({sizes[m]}):",
                f"        for lane in range({LANES}):",
                "            if live[lane]:",
                f"                scratch[{act[m]} + n, lane] = _saturate(scratch[{act[m]} + n, lane])",
            ]
        else:
            lines += [
                f"    _sigmoid_rows(scratch, {act[m] + first}, {rows}, live)"
                for first, rows in groups
            ]
    for j in range(top + 1):
        n_j, h = sizes[j], hist[j]
        for r in range(spec.delays, 0, -1):
            lines.append(f"    _copy_tile(state, {h + r * n_j}, state, {h + (r - 1) * n_j}, {n_j})")
        lines.append(f"    _copy_tile(state, {h}, scratch, {act[j]}, {n_j})")
    lines += [
        f"    _copy_tile(out, 0, scratch, {act[top]}, {sizes[top]})",
        "",
        "",
        "@njit(cache=True)",
        "def batch(weights, state, inputs, out):",
        f"    w = np.zeros(({spec.weight_count}, {LANES}))",
        f"    st = np.zeros(({state_size(spec)}, {LANES}))",
        f"    x = np.zeros(({sizes[0]}, {LANES}))",
        f"    y = np.empty(({sizes[top]}, {LANES}))",
        f"    scratch = np.empty(({scratch_size(spec)}, {LANES}))",
        f"    live = np.zeros({LANES}, dtype=np.uint8)",
        f"    for first in range(0, weights.shape[0], {LANES}):",
        f"        n = min({LANES}, weights.shape[0] - first)",
        f"        for lane in range({LANES}):",
        "            live[lane] = lane < n",
        "            for i in range(w.shape[0]):",
        "                w[i, lane] = weights[first + lane, i] if lane < n else 0.0",
        "            for i in range(st.shape[0]):",
        "                st[i, lane] = state[first + lane, i] if lane < n else 0.0",
        "            for i in range(x.shape[0]):",
        "                x[i, lane] = inputs[first + lane, i] if lane < n else 0.0",
        "        kernel(w, st, x, y, scratch, live)",
        "        for lane in range(n):",
        "            for i in range(st.shape[0]):",
        "                state[first + lane, i] = st[i, lane]",
        "            for i in range(y.shape[0]):",
        "                out[first + lane, i] = y[i, lane]",
    ]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- disk cache of generated code

KERNEL_FORMAT = 2
"""Version of the generated-module format; bump it when generated code changes meaning
without its text changing (it is part of every cached module's name)."""

CACHE_ENV = "EVOCOLONY_KERNEL_CACHE"
"""Environment variable naming the kernel cache directory (overrides the default)."""


def _private_dir(path: Path) -> bool:
    """True if `path` is (now) a directory only this user can write: safe to import code from."""
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        info = path.stat()
    except OSError:
        return False
    mine = not hasattr(os, "getuid") or info.st_uid == os.getuid()
    shared = info.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
    return stat.S_ISDIR(info.st_mode) and mine and not shared and os.access(path, os.W_OK)


@cache
def _fallback_dir() -> Path:
    """A per-user directory under the temp dir, or a fresh private one (cache lost at exit)."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    path = Path(tempfile.gettempdir()) / f"evocolony-kernels-{uid}"
    return path if _private_dir(path) else Path(tempfile.mkdtemp(prefix="evocolony-kernels-"))


def kernel_cache_dir() -> Path:
    """Where generated kernels and numba's machine code for them live.

    `$EVOCOLONY_KERNEL_CACHE`, else `$XDG_CACHE_HOME/evocolony/kernels`, else
    `~/.cache/evocolony/kernels`; if that cannot be made a directory writable only by this
    user, a per-user directory under the temp dir. Imported code must not be writable by others.
    """
    chosen = os.environ.get(CACHE_ENV)
    if chosen:
        path = Path(chosen).expanduser()
    else:
        xdg = os.environ.get("XDG_CACHE_HOME")
        path = (Path(xdg) if xdg else Path.home() / ".cache") / "evocolony" / "kernels"
    return path if _private_dir(path) else _fallback_dir()


@cache
def _file_digest(path: str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _write_atomically(path: Path, data: bytes) -> None:
    """Replace `path` by `data` in one step: readers see the old file or the new, never a part."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _drop_unreadable_machine_code(pycache: Path, name: str) -> None:
    """Delete numba's cache index of module `name` if it or a data file it names is unreadable.

    numba raises on a truncated or corrupt cache file instead of recompiling; without the
    index it recompiles and rewrites both. Run after the module is imported (the data files
    name it); numba reads them lazily, on the first call.
    """
    for index in pycache.glob(f"{name}.*.nbi"):
        try:
            with index.open("rb") as f:
                pickle.load(f)  # numba's format version
                _, overloads = pickle.loads(f.read())
            for data_name in overloads.values():
                data = pycache / data_name
                if data.exists():
                    pickle.loads(data.read_bytes())
        except FileNotFoundError:
            continue  # another process is replacing it
        except Exception:
            index.unlink(missing_ok=True)


_IMPORT_LOCK = threading.RLock()


def cached_module(
    kind: str, source: str, depends: Sequence[str] = (), directory: Path | None = None
) -> ModuleType:
    """Import generated `source` as a real module file, so `@njit(cache=True)` in it works.

    The file is `<directory>/evocolony_<kind>_<hash>.py`, the hash over the source, KERNEL_FORMAT,
    the numba version and the bytes of every file in `depends` (the modules whose compiled
    functions the source calls: numba's cache of the generated code would not notice their
    changes, a new name does). An existing file whose bytes differ (partial write, corruption)
    is rewritten, and unreadable numba cache files of it are dropped (recompiled); writes are
    atomic, so concurrent processes are safe, and one import at a time runs in a process, so
    concurrent threads are too. Imported once per process (kept in `sys.modules`, where
    modules generated later import it from).
    """
    if not kind.isidentifier():
        raise ValueError(f"kind must be an identifier, got {kind!r}")
    key = hashlib.sha256()
    for part in (source, str(KERNEL_FORMAT), numba.__version__, *map(_file_digest, depends)):
        key.update(part.encode())
        key.update(b"\0")
    name = f"evocolony_{kind}_{key.hexdigest()[:32]}"
    # One import at a time: the module sits in sys.modules while its body runs, and another
    # thread must not take it half executed (re-entrant: generated modules load others).
    with _IMPORT_LOCK:
        return sys.modules.get(name) or _load(name, source, directory)


def _load(name: str, source: str, directory: Path | None) -> ModuleType:
    """Write (if needed) and import the generated module `name`; callers hold _IMPORT_LOCK."""
    folder = kernel_cache_dir() if directory is None else directory
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    path = folder / f"{name}.py"
    data = f"# evocolony generated module {name}\n{source}".encode()
    try:
        intact = path.read_bytes() == data
    except OSError:
        intact = False
    if not intact:
        _write_atomically(path, data)
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot import generated module {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    _drop_unreadable_machine_code(folder / "__pycache__", name)  # numba reads it on first call
    return module


@cache
def _module(spec: NetworkSpec) -> ModuleType:
    """The generated module of `spec` (`kernel`, `batch`): disk-cached source and machine code."""
    return cached_module("net", _kernel_source(spec), (__file__,))


def kernel_module(spec: NetworkSpec) -> str:
    """Name of the imported generated module holding `spec_kernel(spec)` as `kernel`.

    For code generated elsewhere that calls the kernel from disk-cached numba functions
    (`from <name> import kernel`): a dispatcher captured in a closure cannot be cached.
    """
    return _module(spec).__name__


def spec_kernel(spec: NetworkSpec) -> Kernel:
    """`step_one` specialised to `spec`, for a tile of LANES controllers at once.

    kernel(w, state, inputs, out, scratch, live): float64 C arrays with one column per lane,
    w (n_weights, LANES), state (state_size, LANES) advanced in place, inputs (inputs, LANES),
    out (outputs, LANES) receiving the raw outputs, scratch (scratch_size, LANES) work space;
    live (LANES,) uint8, 0 for an idle lane (its weights must be 0: its column stays 0).
    Each live lane is bit-identical to `step_one` with `kernel_plan(spec)`. A numba
    dispatcher: call it from Python or from inside another `@njit` function. Cached per spec in
    the process and on disk (`cached_module`): compiled once per machine (~0.9 s for
    paper-best), later processes load the machine code.
    """
    return cast(Kernel, _module(spec).kernel)


def _checked(
    spec: NetworkSpec, weights: np.ndarray, inputs: np.ndarray, state: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """C-contiguous float64 views of the arguments, or ValueError naming the wrong one."""
    w = np.ascontiguousarray(weights, dtype=np.float64)
    x = np.ascontiguousarray(inputs, dtype=np.float64)
    st = np.ascontiguousarray(state, dtype=np.float64)
    n_weights = spec.weight_count
    if w.ndim != 2 or w.shape[1] != n_weights:
        raise ValueError(f"weights must have shape (batch, {n_weights}), got {w.shape}")
    batch = w.shape[0]
    if x.shape != (batch, spec.inputs):
        raise ValueError(f"inputs must have shape ({batch}, {spec.inputs}), got {x.shape}")
    size = state_size(spec)
    if st.shape != (batch, size):
        raise ValueError(f"state must have shape ({batch}, {size}), got {st.shape}")
    return w, x, st


def step(
    spec: NetworkSpec, weights: np.ndarray, inputs: np.ndarray, state: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One step of a batch: (outputs (B, outputs), new state); the arguments are not modified.

    The canonical path (`spec_kernel(spec)`, tile by tile), bit-identical for any batch
    size and to the simulator's episodes.
    """
    w, x, st = _checked(spec, weights, inputs, state)
    new_state = st.copy()
    out = np.empty((w.shape[0], spec.outputs), dtype=np.float64)
    _module(spec).batch(w, new_state, x, out)
    return out, new_state


def _saturate_array(u: np.ndarray) -> np.ndarray:
    a: np.ndarray = np.where(np.isnan(u), 0.0, np.clip(u, -LINEAR_BOUND, LINEAR_BOUND))
    return a


def _sigmoid_array(u: np.ndarray) -> np.ndarray:
    e = np.exp(-np.abs(u))
    a: np.ndarray = np.where(u >= 0.0, 1.0 / (1.0 + e), e / (1.0 + e))
    return a


def step_reference(
    spec: NetworkSpec, weights: np.ndarray, inputs: np.ndarray, state: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The same contract as `step` in vectorised numpy (no loop over individuals, no BLAS).

    Agrees with `step` to rounding (exp may differ in the last ulp); used as its test oracle.
    """
    w, x, st = _checked(spec, weights, inputs, state)
    lay = layout(spec)
    batch = w.shape[0]
    slots = spec.delays + 1
    sizes = spec.sizes
    # history[j][:, r, :] = a_j(k - 1 - r) for the step being computed
    history: list[np.ndarray] = []
    offset = 0
    for n_j in sizes:
        history.append(st[:, offset : offset + slots * n_j].reshape(batch, slots, n_j))
        offset += slots * n_j
    act: list[np.ndarray] = [x]
    for m in range(1, spec.layers + 1):
        u = np.zeros((batch, sizes[m]))
        for blk in lay.blocks:
            if blk.m != m:
                continue
            if blk.s == 0 and blk.t == 0:
                src = act[blk.src]
            elif blk.s == 0:
                src = history[blk.src][:, blk.t - 1, :]
            else:
                src = history[blk.src][:, blk.t, :]
            mat = lay.view(w, blk)
            with np.errstate(over="ignore", invalid="ignore"):  # saturated below, as in `step`
                u = u + (mat[:, :, :-1] * src[:, None, :]).sum(axis=-1) + mat[:, :, -1]
        linear = m == spec.layers and spec.output_activation == "linear"
        act.append(_saturate_array(u) if linear else _sigmoid_array(u))
    new_state = np.concatenate(
        [
            np.concatenate([a[:, None, :], h[:, :-1, :]], axis=1).reshape(batch, -1)
            for a, h in zip(act, history, strict=True)
        ],
        axis=1,
    )
    return act[-1].copy(), new_state


def motor_commands(spec: NetworkSpec, outputs: np.ndarray) -> np.ndarray:
    """Wheel commands from raw outputs: 2y - 1 for sigmoid, y if linear; clipped to [-1, 1].

    Always finite: a NaN output gives 0 (the wheel stops), +-inf gives +-1. Sigmoid outputs are
    in [0, 1], so the clip changes nothing for them.
    """
    y = np.asarray(outputs, dtype=np.float64)
    if y.ndim == 0 or y.shape[-1] != spec.outputs:
        raise ValueError(f"outputs must have last dimension {spec.outputs}, got {y.shape}")
    raw = y if spec.output_activation == "linear" else 2.0 * y - 1.0
    motors: np.ndarray = np.where(np.isnan(raw), 0.0, np.clip(raw, -1.0, 1.0))
    return motors


@njit(cache=True)
def motor_one(out_row: np.ndarray, linear_output: int, motor_row: np.ndarray) -> None:
    """Compiled `motor_commands` for one robot: writes motor_row from out_row (same bits)."""
    for i in range(out_row.shape[0]):
        y = out_row[i] if linear_output != 0 else 2.0 * out_row[i] - 1.0
        if math.isnan(y):
            motor_row[i] = 0.0
        elif y > 1.0:
            motor_row[i] = 1.0
        elif y < -1.0:
            motor_row[i] = -1.0
        else:
            motor_row[i] = y
