"""The sequential cost of a compiled JAX program, read from its optimized HLO.

On a GPU a batched step's latency is set by how many kernels run one after the other and how
many loop trips the host drives (XLA runs a ``while`` loop's control on the host: a round trip
of about 10 µs per trip), not by its FLOPs. Both counts are properties of the compiled program,
so they can be read on any machine, a CPU included (:func:`sequential_cost`):

* ``ops``: the instructions executed in sequence, each fusion, custom call (a LAPACK, cuSOLVER
  or cuBLAS routine), copy or other non-trivial instruction counting one (on a GPU each is
  at least one kernel launch), a ``while`` loop's body and condition counted once per trip, a
  conditional's largest branch once. Bookkeeping that launches nothing (parameters,
  constants, tuples, ``get-tuple-element``, bitcasts) counts zero.
* ``trips``: loop iterations executed, nested loops multiplied.
* ``bytes``: what the executed instructions read and write, each operand and output counted
  once: where a large batch makes the step bound by memory, its time is at least ``bytes``
  over the memory's bandwidth.

A CPU and a GPU compile the same program with different fusion decisions, so the counts differ
between backends by a small factor; the dependency chain (a loop of ``K`` dependent updates
per sweep, say) is the same. Loops whose trip count XLA does not know statically (a
``lax.while_loop`` on data) are counted once and reported in ``unknown_trip_loops``.

A GPU's program can be read without a GPU: XLA compiles for a GPU described by a target
configuration (:func:`deviceless_gpu`, "deviceless" ahead-of-time compilation), with the same
fusion passes as on the device but no autotuning, so library calls stand where the device
might pick Triton matrix-product fusions. On the step of ``benchmarks/step_cost.py`` its counts
equal an H200's kernels part by part where no library routine intervenes; a cuSOLVER or cuBLAS
routine counts one and launches several kernels (``benchmarks/RESULTS.md``).
"""

from __future__ import annotations

import gzip
import json
import os
import re
import sys
import tempfile
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from softcrawl.jaxsim.gpu import set_target, target_capability

#: Opcodes that launch no kernel.
FREE_OPCODES = frozenset({"parameter", "constant", "get-tuple-element", "tuple", "bitcast", "after-all",
                          "partition-id", "replica-id", "opt-barrier", "domain"})

_HEADER = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s*\(.*\)\s*->.*\{\s*$")
_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?[\w.\-]+\s*=\s*.*?\s([a-z][\w\-]*)\((.*)$")


@dataclass(frozen=True)
class SequentialCost:
    """What :func:`sequential_cost` counts (module doc) for one run of a program.

    Attributes:
        ops: instructions executed in sequence. trips: loop iterations executed.
        loops: ``while`` loops in the program (statically, nested ones once).
        unknown_trip_loops: loops of unknown trip count (counted as one trip).
        bytes: the bytes the executed instructions touch, each instruction's operands and
            output counted whole once (library calls' scratch buffers left out): an estimate of
            the memory traffic, high for an instruction that reads a slice of an operand, low
            for a product whose tiles are read more than once.
        by_scope: ``{scope: (ops, bytes)}``, split by the first of the ``scopes`` asked for
            (names given to :func:`jax.named_scope`) that each instruction's JAX ``op_name``
            holds, ``"other"`` for none; empty when no scopes were asked for.
    """

    ops: int
    trips: int
    loops: int
    unknown_trip_loops: int
    bytes: int = 0
    by_scope: dict = field(default_factory=dict)


class _Tally:
    """Running counts of :func:`sequential_cost` for one computation."""

    def __init__(self):
        self.ops = self.trips = self.loops = self.unknown = self.bytes = 0
        self.split_ops: Counter = Counter()
        self.split_bytes: Counter = Counter()

    def add(self, other: "_Tally", n: int = 1) -> None:
        """Add ``n`` runs of ``other`` (loops and unknown loops once: they are static counts)."""
        self.ops += n * other.ops
        self.trips += n * other.trips
        self.bytes += n * other.bytes
        self.loops += other.loops
        self.unknown += other.unknown
        for k, v in other.split_ops.items():
            self.split_ops[k] += n * v
        for k, v in other.split_bytes.items():
            self.split_bytes[k] += n * v


def _computations(text: str) -> tuple[dict[str, list[str]], str]:
    """``{name: instruction lines}`` of an HLO module's text, and the entry computation's name."""
    comps: dict[str, list[str]] = {}
    entry, name = "", None
    for line in text.splitlines():
        if name is None:
            m = _HEADER.match(line)
            if m:
                name = m.group(1)
                comps[name] = []
                if line.startswith("ENTRY"):
                    entry = name
        elif line.strip() == "}":
            name = None
        else:
            comps[name].append(line)
    if not entry:
        raise ValueError("no ENTRY computation in the HLO text")
    return comps, entry


def _attr(line: str, key: str) -> str | None:
    m = re.search(rf"\b{key}=%?([\w.\-]+)", line)
    return m.group(1) if m else None


def _trip_count(line: str) -> int | None:
    m = re.search(r'"known_trip_count"\s*:\s*\{\s*"n"\s*:\s*"(\d+)"', line)
    return int(m.group(1)) if m else None


def _scope(op_name: str, scopes: tuple[str, ...]) -> str:
    """The first of ``scopes`` that the JAX ``op_name`` holds as a path component, else ``"other"``."""
    return next((sc for sc in scopes if f"/{sc}/" in op_name + "/"), "other")


_DEF = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*(\([^()]*\)|\S+)\s")
_ARRAY = re.compile(r"\b(pred|s8|u8|s16|u16|f16|bf16|s32|u32|f32|s64|u64|f64|c64|c128)\[([\d,]*)\]")
_ITEM = {"pred": 1, "s8": 1, "u8": 1, "s16": 2, "u16": 2, "f16": 2, "bf16": 2, "s32": 4, "u32": 4, "f32": 4,
         "s64": 8, "u64": 8, "f64": 8, "c64": 8, "c128": 16}


def _shape_bytes(shape: str, scratch: bool = False) -> int:
    """Bytes of the arrays of an HLO shape (a tuple's elements summed); with ``scratch``, byte
    arrays (``s8``/``u8``: a library call's workspace) left out."""
    total = 0
    for dtype, dims in _ARRAY.findall(shape):
        if scratch and dtype in ("s8", "u8"):
            continue
        n = _ITEM[dtype]
        for d in filter(None, dims.split(",")):
            n *= int(d)
        total += n
    return total


def sequential_cost(hlo_text: str, scopes: tuple[str, ...] = ()) -> SequentialCost:
    """The sequential cost (module doc) of an optimized HLO module (``compiled.as_text()``),
    split by ``scopes`` where given (:class:`SequentialCost`).

    Raises:
        ValueError: text without an ENTRY computation.
    """
    comps, entry = _computations(hlo_text)
    names = _op_names(hlo_text) if scopes else {}
    shapes = {m.group(1): m.group(2) for m in map(_DEF.match, hlo_text.splitlines()) if m}
    memo: dict[str, _Tally] = {}

    def walk(name: str) -> _Tally:
        if name in memo:
            return memo[name]
        t = _Tally()
        for line in comps.get(name, ()):
            m = _INSTR.match(line)
            if not m:
                continue
            opcode = m.group(1)
            if opcode in FREE_OPCODES:
                continue
            if opcode == "while":
                n = _trip_count(line)
                t.unknown += n is None
                n = 1 if n is None else n
                t.loops += 1
                t.trips += n
                t.add(walk(_attr(line, "body")), n)
                t.add(walk(_attr(line, "condition")), n)
                continue
            if opcode == "call":
                t.add(walk(_attr(line, "to_apply")))
                continue
            if opcode == "conditional":
                branches = re.findall(r"%?([\w.\-]+)", (re.search(r"branch_computations=\{([^}]*)\}", line)
                                                         or re.search(r"()", "")).group(1))
                branches += [b for b in (_attr(line, "true_computation"), _attr(line, "false_computation")) if b]
                tallies = [walk(b) for b in branches] or [_Tally()]
                big = max(tallies, key=lambda c: c.ops)
                t.add(big)
                t.trips += max(c.trips for c in tallies) - big.trips
                t.loops += sum(c.loops for c in tallies) - big.loops
                t.unknown += sum(c.unknown for c in tallies) - big.unknown
            d = _DEF.match(line)
            operands = set(re.findall(r"%([\w.\-]+)", m.group(2).split(")", 1)[0]))
            b = _shape_bytes(d.group(2) if d else "", scratch=opcode == "custom-call") + sum(
                _shape_bytes(shapes.get(o, "")) for o in operands)
            t.ops += 1
            t.bytes += b
            if scopes:
                key = _scope(names.get(d.group(1) if d else "", ""), scopes)
                t.split_ops[key] += 1
                t.split_bytes[key] += b
        memo[name] = t
        return t

    t = walk(entry)
    split = {k: (t.split_ops[k], t.split_bytes[k]) for k in t.split_ops}
    return SequentialCost(t.ops, t.trips, t.loops, t.unknown, t.bytes, split)


def xla_flops(compiled) -> float:
    """FLOPs of a compiled program by XLA's cost analysis (``compiled.cost_analysis()``); XLA counts
    a loop body once, whatever its trip count."""
    ca = compiled.cost_analysis()
    if isinstance(ca, (list, tuple)):
        ca = ca[0]
    return float(ca.get("flops", 0.0))


def summary(compiled) -> str:
    """One JSON line of :func:`sequential_cost` and :func:`xla_flops` of a compiled program."""
    c = sequential_cost(compiled.as_text())
    return json.dumps({"ops": c.ops, "trips": c.trips, "loops": c.loops, "unknown_trip_loops": c.unknown_trip_loops,
                       "flops": xla_flops(compiled)})


def _op_names(hlo_text: str) -> dict[str, str]:
    """``{instruction name: its JAX op_name}`` from an optimized HLO module's metadata, with
    `` @ file:line`` where the metadata has a source file."""
    out = {}
    for m in re.finditer(r'^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?metadata=\{([^}]*)\}', hlo_text, re.M):
        meta = {k: v.strip('"') for k, v in re.findall(r'(\w+)=("[^"]*"|\S+)', m.group(2))}
        name = meta.get("op_name", "")
        if meta.get("source_file"):
            name += f' @ {meta["source_file"].rsplit("/", 1)[-1]}:{meta.get("source_line", "")}'
        out.setdefault(m.group(1), name)
    return out


def kernel_profile(trace_dir, hlo_text: str, steps: int, top: int | None = 25, scopes: tuple[str, ...] = ()) -> dict:
    """What the device ran in a trace that :func:`jax.profiler.trace` wrote with
    ``create_perfetto_trace=True`` (its newest ``perfetto_trace.json.gz`` under ``trace_dir``).

    Events that carry an ``hlo_op`` are the program's kernels (on a GPU the device's streams, on a
    CPU the executor's thunks). Returns a dict: ``kernels_per_step`` (kernel events over
    ``steps``), ``busy_us_per_step`` (the union of their intervals), ``window_us_per_step`` (first
    start to last end), ``kernel_us_per_step`` (their summed durations), and ``top``: the ``top``
    instructions by summed duration with their count, microseconds per step and the JAX
    ``op_name`` of their HLO instruction in ``hlo_text`` (the compiled program traced); with
    ``scopes`` (names given to :func:`jax.named_scope`), ``by_scope``: kernels and microseconds
    per step of the instructions whose ``op_name`` holds each scope (the first that matches;
    ``"other"`` for none).

    Raises:
        FileNotFoundError: no trace under ``trace_dir``.
    """
    traces = sorted(Path(trace_dir).rglob("perfetto_trace.json.gz"), key=lambda p: p.stat().st_mtime)
    if not traces:
        raise FileNotFoundError(f"no perfetto_trace.json.gz under {trace_dir}")
    with gzip.open(traces[-1], "rt") as f:
        events = json.load(f)["traceEvents"]
    pname = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    kernels = [e for e in events if e.get("ph") == "X" and "hlo_op" in e.get("args", {})
               and not e["name"].startswith("end: ")]
    device = [e for e in kernels if not pname.get(e["pid"], "/host").startswith("/host")]
    kernels = device or kernels
    if not kernels:
        return {**({"by_scope": {}} if scopes else {}), "kernels_per_step": 0, "busy_us_per_step": 0.0,
                "window_us_per_step": 0.0, "kernel_us_per_step": 0.0, "top": []}
    spans = sorted((float(e["ts"]), float(e["ts"]) + float(e["dur"])) for e in kernels)
    busy, (lo, hi) = 0.0, spans[0]
    for a, b in spans[1:]:
        if a > hi:
            busy, lo = busy + hi - lo, a
        hi = max(hi, b)
    busy += hi - lo
    by_op: dict[str, list[float]] = {}
    for e in kernels:
        by_op.setdefault(e["args"]["hlo_op"], []).append(float(e["dur"]))
    names = _op_names(hlo_text)
    rows = sorted(by_op.items(), key=lambda kv: -sum(kv[1]))
    by_scope: dict[str, list[float]] = {}
    for op, d in rows:
        key = _scope(names.get(op, ""), scopes)
        tot = by_scope.setdefault(key, [0.0, 0.0])
        tot[0], tot[1] = tot[0] + len(d) / steps, tot[1] + sum(d) / steps
    rows = rows if top is None else rows[:top]
    out = {"by_scope": {k: {"kernels": n, "us": us} for k, (n, us) in by_scope.items()}} if scopes else {}
    return {**out, "kernels_per_step": len(kernels) / steps, "busy_us_per_step": busy / steps,
            "window_us_per_step": (max(b for _, b in spans) - spans[0][0]) / steps,
            "kernel_us_per_step": sum(float(e["dur"]) for e in kernels) / steps,
            "top": [{"op": op, "count": len(d), "us_per_step": sum(d) / steps, "op_name": names.get(op, "")}
                    for op, d in rows]}


#: Environment for :func:`deviceless_gpu`, set before JAX starts its backends: the CUDA plugin
#: starts without a device (``cuInit`` fails on a machine without a driver) and uses none that
#: is present; XLA's Triton matrix products are off, their tile sizes need autotuning on a device.
DEVICELESS_ENV = {"JAX_SKIP_CUDA_CONSTRAINTS_CHECK": "1", "CUDA_VISIBLE_DEVICES": "-1"}
DEVICELESS_XLA_FLAGS = "--xla_gpu_enable_triton_gemm=false"


#: Environment that makes XLA log ptxas' report of every kernel it compiles for a GPU (registers
#: a thread, bytes spilled to local memory), where XLA runs ptxas as a program (the CUDA
#: plugin's, as in deviceless compilation): :func:`ptxas_report` reads it.
PTXAS_REPORT_ENV = {"TF_CPP_MIN_LOG_LEVEL": "0", "TF_CPP_VMODULE": "subprocess_compilation=3"}


def prepare_deviceless_gpu(ptxas_report: bool = False) -> None:
    """Set :data:`DEVICELESS_ENV` and :data:`DEVICELESS_XLA_FLAGS` in ``os.environ`` (and
    :data:`PTXAS_REPORT_ENV` with ``ptxas_report``); call it before anything starts JAX's
    backends (creating an array does)."""
    os.environ.update(DEVICELESS_ENV)
    if ptxas_report:
        os.environ.update(PTXAS_REPORT_ENV)
    flags = os.environ.get("XLA_FLAGS", "")
    if DEVICELESS_XLA_FLAGS not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {DEVICELESS_XLA_FLAGS}".strip()


def deviceless_gpu(target_config: str):
    """A sharding on one NVIDIA GPU that need not be present, for ahead-of-time compilation:
    ``jax.jit(f).lower(*specs).compile()`` with ``jax.ShapeDtypeStruct`` arguments carrying it
    compiles ``f`` for that GPU on any machine (module doc). The compiled program can be read
    (``as_text()``), not run. The target's compute capability is recorded
    (:func:`softcrawl.jaxsim.gpu.set_target`): the step's kernel forms follow it as on that GPU.

    Args:
        target_config: an XLA ``GpuTargetConfig`` in protobuf text format (the device's
            description: compute capability, cores, memory; ``benchmarks/gpu_targets/``).

    Raises:
        RuntimeError: JAX has no CUDA plugin, or it started without :func:`prepare_deviceless_gpu`
            (the plugin of the installed JAX's version: ``pip install
            "jax-cuda12-plugin[with-cuda]==<jax version>"``).
        ValueError: a configuration without a CUDA compute capability.
    """
    import jax
    from jax.experimental import topologies

    try:
        topo = topologies.get_topology_desc(platform="cuda", target_config=target_config, topology="1x1x1")
    except (NotImplementedError, RuntimeError) as e:
        raise RuntimeError("compiling for a GPU without one needs JAX's CUDA plugin of the installed JAX's version "
                           f'(pip install "jax-cuda12-plugin[with-cuda]=={jax.__version__}"), started after '
                           "softcrawl.jaxsim.cost.prepare_deviceless_gpu()") from e
    mesh = topologies.make_mesh(topo, (1,), ("gpu",))
    set_target(target_capability(target_config))  # the kernels' forms and sizes follow the target
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())


_PTXAS_KERNEL = re.compile(r"Function properties for (\S+)\s*\n\s*(\d+) bytes stack frame, (\d+) bytes spill stores, "
                           r"(\d+) bytes spill loads\s*\n.*?Used (\d+) registers")


def ptxas_report(log: str) -> dict[str, dict[str, int]]:
    """Each kernel's ptxas report in a compilation's log (:data:`PTXAS_REPORT_ENV`): ``{name:
    {"registers": a thread, "spill_stores": bytes, "spill_loads": bytes, "stack": bytes}}``. A
    kernel that spills reads and writes local memory (the L1 cache, else device memory) where
    it would use registers."""
    return {m.group(1): {"registers": int(m.group(5)), "spill_stores": int(m.group(3)),
                         "spill_loads": int(m.group(4)), "stack": int(m.group(2))}
            for m in _PTXAS_KERNEL.finditer(log)}


@contextmanager
def captured_stderr():
    """The process's standard error (file descriptor 2, where XLA's C++ logs go) redirected to a
    temporary file while the block runs; yields a list that receives its text at the end."""
    out: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as f:
        os.dup2(f.fileno(), 2)
        try:
            yield out
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            f.seek(0)
            out.append(f.read().decode("utf-8", "replace"))
