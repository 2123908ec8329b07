"""The sequential cost of the JAX vector env's physics step, on any machine, and its speed where a
GPU is present.

The program measured is the JAX backend's rollout of one action (:func:`softcrawl.jaxsim.rig.make_action_rollout`,
what :class:`softcrawl.envs.backends.jaxvec.JaxBackend` runs per vectorised step) for a batch of a
preset's designs with as many leg slots as its largest design, lowered and compiled for JAX's
default device. Printed as one JSON line (per batch size when timing):

* ``dependent_ops_per_step``: operations executed in sequence per physics step (each loop
  body's operations times its trips, plus those outside loops; a fusion or a library call
  counts one: :func:`softcrawl.jaxsim.cost.sequential_cost`), from the compiled rollout of
  ``--steps`` steps divided by ``--steps``;
* ``loop_trips_per_step``: loop iterations executed per physics step (the rollout's own loop
  over steps counts one; XLA on a GPU runs a loop's control on the host, about 10 us a trip);
* ``mflop_per_robot_step``: XLA's cost analysis of the one-step rollout, per robot (exact when
  the step has no loop of its own, ``inner_loops`` 0: XLA counts a loop body once);
* with ``--time`` (the default on a GPU): ``ms_per_step`` and ``robot_steps_per_s`` at each of
  ``--batches`` (random designs, landed for one action first; ``bad_robots``: robots whose state
  went invalid; ``peak_device_memory_gb``: the device's peak memory in use so far, where JAX
  reports it);
* with ``--reference FILE`` too: each batch's disk nodes after its timed calls against those a
  run of another form of the step stored in ``FILE`` for the same robots (:func:`against_reference`:
  ``reference_max_node_distance_mm``, the 99th percentile and median of the robots' largest,
  the robots invalid in one run only), or stored there for the runs after it;
* ``ops_by_scope``: ``dependent_ops_per_step`` split by the step's parts (``STEP_SCOPES``);
  ``mb_per_robot_step`` (and by part): the bytes the step's operations touch per robot, each
  operation's operands and output counted once (:class:`softcrawl.jaxsim.cost.SequentialCost`);
* with ``--gpu-target CONFIG`` instead: the same counts of the program compiled for the GPU
  that an XLA target configuration describes (``benchmarks/gpu_targets/h100.pbtxt``), on any
  machine, at each of ``--batches``, nothing timed (:func:`softcrawl.jaxsim.cost.deviceless_gpu`;
  needs JAX's CUDA plugin: ``pip install "jax-cuda12-plugin[with-cuda]==<jax version>"``, best
  in a separate environment), and what the bytes cost at the GPU's memory bandwidth:
  ``bandwidth_floor_ms_per_step`` and the ``bandwidth_bound_robot_steps_per_s`` it allows, and
  ``device_memory_gb``, the memory the program needs on the GPU (XLA's memory analysis:
  arguments, outputs and temporary buffers; the largest batch a card holds); with
  ``--registers`` also ptxas' report of the kernels (:func:`softcrawl.jaxsim.cost.ptxas_report`):
  ``ptxas.spilling`` (bytes spilled by kernel) and the five that use the most registers;
* with ``--profile DIR``: one more call at each timed batch ``B`` under JAX's profiler, its
  trace in ``DIR/bB`` and, printed as one JSON line, the kernels per step, the device's busy time
  per step and the kernels that cost most, each with the JAX operation it came from
  (:func:`softcrawl.jaxsim.cost.kernel_profile`; all of them in ``DIR/bB/kernels.json``, the
  compiled program in ``DIR/bB/step.hlo.txt``; ``by_scope``: the step's parts).

Usage:
    python benchmarks/step_cost.py [--preset paper] [--precision float32] [--solver apgd]
        [--iterations N] [--delassus dense16] [--rid-form rows] [--cholesky library]
        [--pairs-dot TF32_TF32_F32_X3] [--resident-rows 128] [--unroll-pivots 36] [--selection kernel]
        [--elimination kernel]
        [--formed-operator] [--batch 2] [--steps 50] [--time]
        [--batches 96,1024,16384] [--calls 5]
        [--profile DIR] [--reference FILE]
    python benchmarks/step_cost.py --gpu-target benchmarks/gpu_targets/h100.pbtxt --batches 96,1024,16384 [--registers]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import platform
import re
import time
from pathlib import Path


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper", help="the training preset whose robots and designs are stepped")
    p.add_argument("--precision", choices=("float32", "float64"), default="float32")
    p.add_argument("--solver", choices=("apgd", "pgs"), default="apgd")
    p.add_argument("--iterations", type=int, default=None, help="contact solver iterations (default: the solver's)")
    p.add_argument("--delassus", choices=("dense", "dense16", "fused16", "blocks"), default=None,
                   help="how the accelerated gradient applies the Delassus operator (Settings.delassus; "
                        "default: the engine's for the precision)")
    p.add_argument("--rid-form", choices=("rows", "pairs", "kernel"), default=None,
                   help="the legs' RID terms' form (Settings.rid_form; default: by platform)")
    p.add_argument("--pairs-dot", default=None, metavar="PRESET",
                   help="the pairs form's product's dot algorithm in float32, a jax.lax.DotAlgorithmPreset name "
                        "(softcrawl.jaxsim.legs.PAIRS_DOT_ALGORITHM; default: full float32)")
    p.add_argument("--resident-rows", type=int, default=None, metavar="ROWS",
                   help="the solve kernel holds the operator on chip, by blocks of ROWS rows, its products on the "
                        "tensor cores (softcrawl.jaxsim.fused.RESIDENT_ROWS; default: read from the cache every "
                        "iteration)")
    p.add_argument("--unroll-pivots", type=int, default=None, metavar="N",
                   help="the factor kernels unroll their pivots for matrices of up to N rows (36: the legs' "
                        "factors, 72: the attachment block's inverse too; softcrawl.jaxsim.factor.UNROLL_PIVOTS; "
                        "default: the module's)")
    p.add_argument("--selection", choices=("xla", "kernel"), default=None,
                   help="how each body's contact candidates are chosen (softcrawl.jaxsim.candidates.SELECTION: "
                        "XLA's program for all bodies at once, or one kernel, a program a body; default: the "
                        "module's)")
    p.add_argument("--elimination", choices=("xla", "kernel"), default=None,
                   help="how the attachments' elimination forms its products (softcrawl.jaxsim.elimination.FORM: "
                        "XLA's batched products, or one kernel, a program a robot; default: the module's)")
    p.add_argument("--formed-operator", action="store_true",
                   help="the solve kernel reads the condensed operator formed by XLA, not in its parts "
                        "(softcrawl.jaxsim.fused.OPERATOR_PARTS = False)")
    p.add_argument("--cholesky", choices=("library", "kernel"), default=None,
                   help="how the step inverts its Cholesky factors (Settings.cholesky; default: the engine's for "
                        "the precision)")
    p.add_argument("--batch", type=int, default=2, help="robots of the compiled program whose cost is read")
    p.add_argument("--steps", type=int, default=None, help="steps per action (default: the preset's)")
    p.add_argument("--time", action="store_true", help="also time the step (the default where JAX has a GPU)")
    p.add_argument("--batches", default="96,1024,16384", help="batch sizes timed")
    p.add_argument("--calls", type=int, default=5, help="timed calls (one action each) per batch size")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-cost", action="store_true", help="time only: skip the small programs' cost analysis")
    p.add_argument("--profile", default=None, help="trace one more call at each batch into this folder")
    p.add_argument("--registers", action="store_true",
                   help="with --gpu-target: also ptxas' report of the kernels (registers, spills)")
    p.add_argument("--gpu-target", default=None, metavar="CONFIG",
                   help="compile for the GPU this XLA target configuration describes, without one (e.g. "
                        "benchmarks/gpu_targets/h100.pbtxt; needs JAX's CUDA plugin) and print its program's "
                        "sequential cost at each of --batches")
    p.add_argument("--reference", default=None, metavar="FILE",
                   help="with the timing: compare each batch's final disk node positions with those an earlier "
                        "run (another form of the step, the same designs and calls) stored in FILE (.npz), or "
                        "store them there where FILE holds none for that batch")
    p.add_argument("--label", default=None,
                   help="a name for the tree the step comes from, one of the settings each line names (e.g. "
                        "'base': an earlier commit's package first on PYTHONPATH, timed against today's)")
    args = p.parse_args(argv)
    from softcrawl.jaxsim.cost import prepare_deviceless_gpu

    if args.gpu_target:
        target_config = Path(args.gpu_target).read_text()
        prepare_deviceless_gpu(ptxas_report=args.registers)
    import jax

    jax.config.update("jax_enable_x64", args.precision == "float64")
    import jax.numpy as jnp
    import numpy as np

    from softcrawl.codesign.config import preset
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.jaxsim import candidates, elimination, factor, fused, legs
    from softcrawl.jaxsim.cost import (captured_stderr, deviceless_gpu, kernel_profile, ptxas_report,
                                       sequential_cost, xla_flops)
    from softcrawl.jaxsim.engine import STEP_SCOPES, rest_state
    from softcrawl.jaxsim.rig import Rig, make_action_rollout
    from softcrawl.jaxsim.tables import build_table

    cfg = preset(args.preset)
    space, designs = cfg.env.design_space(), cfg.env.designs()
    slots = max(sum(v > 0 for v in d) for d in designs)
    table = build_table(space, factory=robot_factory(cfg), n_slots=slots, solver=args.solver,
                        iterations=args.iterations, delassus=args.delassus, cholesky=args.cholesky)
    settings = dataclasses.replace(table.parts.settings, rid_form=args.rid_form)
    legs.PAIRS_DOT_ALGORITHM = args.pairs_dot
    fused.RESIDENT_ROWS = args.resident_rows
    fused.OPERATOR_PARTS = not args.formed_operator
    if args.unroll_pivots is not None:
        factor.UNROLL_PIVOTS = args.unroll_pivots
    if args.selection is not None:
        candidates.SELECTION = args.selection
    if args.elimination is not None:
        elimination.FORM = args.elimination
    engine = {"precision": args.precision, "solver": settings.solver, "iterations": settings.iterations,
              "delassus": settings.delassus, "rid_form": settings.rid_form, "cholesky": settings.cholesky,
              "pairs_dot": args.pairs_dot, "resident_rows": args.resident_rows,
              "operator_parts": fused.OPERATOR_PARTS, "unroll_pivots": factor.UNROLL_PIVOTS,
              "selection": candidates.SELECTION, "elimination": elimination.FORM,
              "label": args.label}  # what every line was measured with
    steps = args.steps or cfg.env.steps_per_action
    R = space.n_regulators
    rng = np.random.default_rng(args.seed)
    largest = [d for d in designs if sum(v > 0 for v in d) == slots]

    def batch(B, pool, picked=None):
        picked = [pool[i] for i in rng.integers(len(pool), size=B)] if picked is None else picked
        model = dataclasses.replace(table.model(picked), settings=settings)
        dt = model.disk.rest.dtype
        rig = Rig(jnp.ones((B, R), dt), jnp.zeros((B, R), dt), jnp.zeros((B, R), dt), jnp.zeros((B, R), dt))
        return model, rig, rest_state(model)

    def inputs(n_steps, model, rig, state):
        B = state.t.shape[0]
        return model, rig, state, jnp.zeros((B, R), state.x.dtype), jnp.full((B,), n_steps, jnp.int32)

    def lowered(n_steps, *args):
        return make_action_rollout(n_steps).lower(*inputs(n_steps, *args))

    def split(seq, B):
        return {"ops_by_scope": {k: v[0] / steps for k, v in sorted(seq.by_scope.items())},
                "mb_per_robot_step": seq.bytes / steps / B / 1e6,
                "mb_per_robot_step_by_scope": {k: round(v[1] / steps / B / 1e6, 3)
                                               for k, v in sorted(seq.by_scope.items())}}

    if args.gpu_target:
        sharding = deviceless_gpu(target_config)
        bandwidth = float(re.search(r"memory_bandwidth:\s*(\d+)", target_config).group(1))  # bytes/s
        for B in (int(b) for b in args.batches.split(",")):
            specs = jax.tree.map(lambda a: jax.ShapeDtypeStruct(np.shape(a), a.dtype, sharding=sharding),
                                 inputs(steps, *batch(B, designs)))
            with jax.sharding.use_abstract_mesh(sharding.mesh.abstract_mesh):  # Pallas reads the GPU's kind here
                program = make_action_rollout(steps).lower(*specs)
            with captured_stderr() if args.registers else contextlib.nullcontext([""]) as log:
                compiled = program.compile()
            text = compiled.as_text()
            seq = sequential_cost(text, STEP_SCOPES)
            registers = {}
            if args.registers:
                kernels = ptxas_report(log[0])
                registers = {"ptxas": {
                    "kernels": len(kernels),
                    "spilling": {k: v["spill_stores"] for k, v in kernels.items() if v["spill_stores"]},
                    "most_registers": sorted(((v["registers"], k) for k, v in kernels.items()), reverse=True)[:5]}}
            floor_s = seq.bytes / steps / bandwidth
            print(json.dumps({"preset": args.preset, "gpu_target": args.gpu_target, "batch": B, **engine,
                              "dependent_ops_per_step": seq.ops / steps,
                              "loop_trips_per_step": seq.trips / steps, **split(seq, B),
                              "bandwidth_floor_ms_per_step": 1e3 * floor_s,
                              "bandwidth_bound_robot_steps_per_s": B / floor_s,
                              "device_memory_gb": device_memory(compiled) / 1e9, **registers,
                              "jax": jax.__version__}), flush=True)
        return
    device = jax.devices()[0]
    out = {"preset": args.preset, "device": f"{device.platform}:{device.device_kind}", "host": platform.node(),
           **engine, "leg_slots": slots, "contacts": settings.disk_contacts + slots * settings.leg_contacts,
           "steps_per_action": steps, "jax": jax.__version__}
    if not args.no_cost:
        small = batch(args.batch, largest)
        t0 = time.perf_counter()
        compiled = lowered(steps, *small).compile()
        compile_s = time.perf_counter() - t0
        seq = sequential_cost(compiled.as_text(), STEP_SCOPES)
        one = lowered(1, *small).compile()
        out.update(compile_s=round(compile_s, 2), dependent_ops_per_step=seq.ops / steps, **split(seq, args.batch),
                   loop_trips_per_step=seq.trips / steps, mflop_per_robot_step=xla_flops(one) / args.batch / 1e6,
                   inner_loops=sequential_cost(one.as_text()).loops, unknown_trip_loops=seq.unknown_trip_loops)
        print(json.dumps(out), flush=True)
    if not (args.time or device.platform == "gpu"):
        return
    for B in (int(b) for b in args.batches.split(",")):
        picked = [designs[i] for i in rng.integers(len(designs), size=B)]
        model, rig, state = batch(B, designs, picked)
        dt = state.x.dtype
        steps_b = jnp.full((B,), steps, jnp.int32)
        land = jnp.zeros((B, R), dt)
        go = jnp.tile(jnp.asarray(np.linspace(90.0, 30.0, R), dt), (B, 1))
        t0 = time.perf_counter()
        roll = make_action_rollout(steps).lower(model, rig, state, land, steps_b).compile()
        state, _ = jax.block_until_ready(roll(model, rig, state, land, steps_b))
        first_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(args.calls):
            state, dead = roll(model, rig, state, go, steps_b)
        jax.block_until_ready(state)
        wall = time.perf_counter() - t0
        agreement = {}
        if args.reference:
            end = {"designs": np.asarray(picked, np.int64), "x": np.asarray(state.x), "dead": np.asarray(dead, bool),
                   "calls": np.asarray(args.calls)}
            agreement = against_reference(args.reference, f"b{B}", end)
        print(json.dumps({"batch": B, "first_call_s": round(first_s, 2),
                          "dependent_ops_per_step": sequential_cost(roll.as_text()).ops / steps,
                          "ms_per_step": 1e3 * wall / (args.calls * steps),
                          "robot_steps_per_s": B * steps * args.calls / wall,
                          "bad_robots": int(np.sum(np.asarray(dead))),
                          "peak_device_memory_gb": (device.memory_stats() or {}).get("peak_bytes_in_use", 0) / 1e9,
                          **agreement, "device": out["device"], **engine, "form_keys": list(engine)}), flush=True)
        if args.profile:
            where = Path(args.profile, f"b{B}")
            with jax.profiler.trace(str(where), create_perfetto_trace=True):
                jax.block_until_ready(roll(model, rig, state, go, steps_b))
            hlo = roll.as_text()
            (where / "step.hlo.txt").write_text(hlo)
            prof = kernel_profile(where, hlo, steps, None, STEP_SCOPES)
            (where / "kernels.json").write_text(json.dumps(prof))
            print(json.dumps({"batch": B, **prof, "top": prof["top"][:25]}), flush=True)


def device_memory(compiled) -> int:
    """Bytes of device memory a compiled program needs while it runs, by XLA's memory analysis:
    its arguments, outputs and temporary buffers, less the outputs that alias arguments."""
    m = compiled.memory_analysis()
    return m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes - m.alias_size_in_bytes


def against_reference(path, key: str, end: dict) -> dict:
    """Compare one batch's end ``end`` (``designs`` ``(B, slots)``, ``x`` ``(B, n, 3)`` the disk
    nodes, mm, ``dead`` ``(B,)``, ``calls``) with the reference stored under ``key`` in the npz
    file ``path``; where the file has no ``key``, store ``end`` there under it instead, keeping
    the file's other batches. Robots invalid in either run are left out of the distances and
    counted.

    Returns:
        ``{"reference": "stored"}``, or the comparison: the largest distance of a disk node from
        its reference position over the robots (``reference_max_node_distance_mm``), the 99th
        percentile and the median of each robot's largest (mm), and the robots invalid in the
        reference or here only.

    Raises:
        ValueError: the reference was made with other designs, calls or disk.
    """
    import numpy as np

    stored = {}
    if Path(path).exists():
        with np.load(path, allow_pickle=False) as f:
            stored = {name: f[name] for name in f.files}
    if f"{key}/x" not in stored:
        stored.update({f"{key}/{name}": v for name, v in end.items()})
        np.savez(path, **stored)
        return {"reference": "stored"}
    ref = {name: stored[f"{key}/{name}"] for name in end}
    for name in ("designs", "calls"):
        if ref[name].shape != end[name].shape or np.any(ref[name] != end[name]):
            raise ValueError(f"{path}: its batch {key} was run with other {name}: compare runs of the same "
                             "--seed, --batches and --calls")
    if ref["x"].shape != end["x"].shape:
        raise ValueError(f"{path}: its batch {key}'s disk has shape {ref['x'].shape}, this run's {end['x'].shape}")
    both = ~(ref["dead"] | end["dead"])
    robot = np.linalg.norm(end["x"][both].astype(float) - ref["x"][both], axis=-1).max(axis=-1, initial=0.0)
    return {"reference_max_node_distance_mm": float(robot.max(initial=0.0)),
            "reference_p99_robot_distance_mm": float(np.percentile(robot, 99)) if robot.size else 0.0,
            "reference_median_robot_distance_mm": float(np.median(robot)) if robot.size else 0.0,
            "bad_robots_reference_only": int(np.sum(ref["dead"] & ~end["dead"])),
            "bad_robots_here_only": int(np.sum(end["dead"] & ~ref["dead"]))}


if __name__ == "__main__":
    main()
