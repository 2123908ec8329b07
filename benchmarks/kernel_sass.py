"""The contact solve kernel's iteration, and the RID kernel's instructions a leg, read from their
machine code without a GPU.

Each variant of :func:`softcrawl.jaxsim.fused.fused_solve` (its module constants ``ROW_BLOCK``,
``NUM_WARPS``, ``LOOP_PRODUCT``, ``RESIDENT_ROWS``) is compiled for the GPU of a target
configuration on this machine (deviceless, :func:`softcrawl.jaxsim.cost.deviceless_gpu`), its
PTX assembled by the CUDA plugin's ``ptxas`` and disassembled by ``nvdisasm``; the last
outermost loop of the machine code is the solve's iterations (:func:`outer_loops`). Printed as
JSON lines, one a variant: ``registers`` a thread and bytes spilled (ptxas),
``loop_instructions`` (SASS instructions an iteration executes per warp: a lower bound on an
iteration's issue cycles is that times the warps over the multiprocessor's four schedulers),
``loops_before`` (the instructions of each loop before it: the operator's preparation, one
trip a block of rows) and the count of each opcode in the loop
(``LDG``: loads from device memory or cache, ``BAR``: barriers, ``SHFL``: shuffles, ``HADD2``:
the float16 conversions), and ``warp_instructions_per_robot`` (:func:`solve_instructions`: the
preparation's and the 48 iterations' instructions, times the warps). A proxy for time where no GPU
is lent, not a measurement.

With ``--kernel rid``, each variant of :func:`softcrawl.jaxsim.ridkernel.rid_kernel_terms` (its
constants ``ELEMENTS``, ``NUM_WARPS``, ``DOT_ALGORITHM``, ``SPLIT``, ``ROW_GROUPS``, ``TILE``) on
the ``paper`` preset's leg: registers, each family's loop of element blocks and the edge loops
inside it (:func:`loop_tree`), and ``warp_instructions_per_leg``, the instructions a leg's programs issue
(each loop's instructions times its trips, times the warps): the kernel does little but
arithmetic, so at the multiprocessors' issue rate (one instruction a cycle per scheduler) that
count bounds its time from below.

With ``--kernel factor``, each variant of :mod:`softcrawl.jaxsim.factor`'s kernels (its constants
``UNROLL_PIVOTS``, ``PER_THREAD``) for the 96-robot step's matrices (576 legs' 36 x 36 step
matrices formed, their factors inverted and the free motion solved, ``step_solve``; 96
attachment blocks' 72 x 72 inverses): registers, spills, ``instructions_per_pivot``
(the pivot loop's, or with the pivots unrolled the straight-line code's share a pivot) and
``warp_instructions_per_matrix`` (that times the pivots and the program's warps): at thousands
of matrices the kernels are bound by the multiprocessors' issue rate.

With ``--kernel elimination``, each variant of :func:`softcrawl.jaxsim.elimination.by_kernel` (its
constants ``NUM_WARPS``, ``ROW_BLOCK``, ``DOT_ALGORITHM``) on the ``paper`` preset's robot (72
attachment rows, 8 disk and 6 x 12 leg contacts): registers, spills, its loops and
``warp_instructions_per_robot`` (its loop over the legs run once a leg, its loop over the legs'
blocks of ``S``'s rows once a leg and block, times the warps).

Needs JAX's CUDA plugin of the installed JAX's version and ``nvdisasm`` (``pip install
"jax-cuda12-plugin[with-cuda]==<jax version>" nvidia-cuda-nvdisasm``).

Usage:
    python benchmarks/kernel_sass.py [--gpu-target benchmarks/gpu_targets/h100.pbtxt]
        [--variants 64:8:0:-,64:8:0:128] [--contacts 80 | --schur 8:6:12]
    python benchmarks/kernel_sass.py --kernel rid [--variants 16:2:SPLIT_BF16:1,16:2:SPLIT_BF16:1:1:32]
    python benchmarks/kernel_sass.py --kernel factor [--variants 0:64,36:128]
    python benchmarks/kernel_sass.py --kernel elimination [--variants 4:128:TF32_TF32_F32_X3,4:128:-]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import shutil
import subprocess
import tempfile
from functools import partial
from pathlib import Path

_SASS = re.compile(r"^\s*/\*([0-9a-f]{4,})\*/\s+(.*?);", re.M)
_LABEL = re.compile(r"^\s*\.(L_x_\d+):\s*\n(?:.*\n)*?\s*/\*([0-9a-f]{4,})\*/", re.M)


#: Each kernel's variants compiled where ``--variants`` names none (the module's constants first).
DEFAULT_VARIANTS = {"solve": "64:8:0:-,64:8:0:128,64:8:0:64",
                    "rid": "16:2:SPLIT_BF16:1,16:2:SPLIT_BF16:1:1:32,16:1:SPLIT_BF16:1:3,16:2:SPLIT_TF32:1,"
                           "16:4:SPLIT_BF16:1,16:2:-:1",
                    "factor": "0:64,72:64,72:128",
                    "elimination": "4:128:TF32_TF32_F32_X3,8:128:TF32_TF32_F32_X3,4:64:TF32_TF32_F32_X3"}


def tool(name: str) -> str:
    """The path of a CUDA tool installed by a pip wheel (``nvidia/*/bin/NAME``).

    Raises:
        FileNotFoundError: no wheel installed it.
    """
    import nvidia

    for root in nvidia.__path__:
        found = sorted(Path(root).glob(f"*/bin/{name}"))
        if found:
            return str(found[-1])
    raise FileNotFoundError(f"{name} not found in the nvidia wheels: pip install nvidia-cuda-nvdisasm "
                            '"jax-cuda12-plugin[with-cuda]==<jax version>"')


def _opcode(text: str) -> str:
    """An instruction's opcode, its predicate and modifiers dropped."""
    return re.sub(r"^@!?U?P\w+\s+", "", text).split()[0].split(".")[0]


def _loops(sass: str):
    """``(instructions, spans, parent)`` of ``nvdisasm -c`` output: ``(address, text)`` of each
    instruction, ``(start, end)`` addresses of each loop in the order of the code (a loop: the
    instructions from a label to the furthest backward branch to it) and the index of the
    innermost loop holding each (None: outermost)."""
    ins = [(int(a, 16), t) for a, t in _SASS.findall(sass)]
    labels = {m.group(1): int(m.group(2), 16) for m in _LABEL.finditer(sass)}
    ends = {}
    for a, t in ins:
        m = re.search(r"BRA\s+`?\(?\.?(L_x_\d+)", t)
        if m and labels.get(m.group(1), a) < a:
            ends[labels[m.group(1)]] = max(a, ends.get(labels[m.group(1)], a))
    spans = sorted(ends.items())
    parent = [min((j for j, (s2, e2) in enumerate(spans) if j != i and s2 <= s and e <= e2),
                  key=lambda j: spans[j][1] - spans[j][0], default=None) for i, (s, e) in enumerate(spans)]
    return ins, spans, parent


def outer_loops(sass: str) -> list[collections.Counter]:
    """The opcodes (predicates and modifiers dropped) of each outermost loop of ``nvdisasm -c``
    output, in the order of the code (:func:`_loops`; outermost: inside no other). In the solve
    kernel the last is the iterations: they follow the loop that prepares the operator."""
    ins, spans, parent = _loops(sass)
    return [collections.Counter(_opcode(t) for a, t in ins if start <= a <= end)
            for (start, end), p in zip(spans, parent) if p is None]


def loop_tree(sass: str) -> list[dict]:
    """Every loop of ``nvdisasm -c`` output in the order of the code (:func:`_loops`): ``parent``
    the index of the innermost loop holding it (None outermost), ``opcodes`` its own
    instructions' opcodes (its inner loops' left out), ``total`` all its instructions."""
    ins, spans, parent = _loops(sass)
    out = []
    for i, (start, end) in enumerate(spans):
        inner = [spans[j] for j in range(len(spans)) if parent[j] == i]
        own = [t for a, t in ins if start <= a <= end and not any(s2 <= a <= e2 for s2, e2 in inner)]
        out.append({"parent": parent[i], "total": sum(start <= a <= end for a, _ in ins),
                    "opcodes": collections.Counter(map(_opcode, own))})
    return out


def issued(sass: str, loops: list[dict], trips: dict[int, int]) -> int:
    """The instructions one warp issues running ``nvdisasm -c`` output ``sass`` whose
    :func:`loop_tree` is ``loops``: the code outside the loops once, each loop's own instructions
    ``trips[i]`` times each time its parent runs (1 where not given)."""
    runs: dict[int, int] = {}
    for i, lp in enumerate(loops):  # parents come before their loops
        runs[i] = trips.get(i, 1) * (1 if lp["parent"] is None else runs[lp["parent"]])
    outside = len(_SASS.findall(sass)) - sum(lp["total"] for lp in loops if lp["parent"] is None)
    return outside + sum(runs[i] * sum(lp["opcodes"].values()) for i, lp in enumerate(loops))


def leg_instructions(sass: str, families, elements: int, split: int, warps: int) -> int | None:
    """The warp instructions a leg's RID kernel programs issue (module doc), from its machine
    code ``sass`` and its families' ``(E, k)`` (elements, nodes an element): the outermost loops
    are the families' loops of element blocks, ``ceil(E / (elements split))`` trips a program,
    each holding a loop over the ``k - 1`` edges for each group of stress rows
    (``ridkernel.row_groups``); None if the code has another shape."""
    loops = loop_tree(sass)
    outer = [i for i, lp in enumerate(loops) if lp["parent"] is None]
    inner = [[j for j, lp in enumerate(loops) if lp["parent"] == i] for i in outer]
    if len(outer) != len(families) or any(not js or any(lp["parent"] in js for lp in loops) for js in inner):
        return None  # not edge loops, without loops of their own, in each family's loop
    trips = {}
    for i, js, (E, k) in zip(outer, inner, families):
        trips[i] = -(-E // (elements * split))
        trips.update({j: k - 1 for j in js})
    return issued(sass, loops, trips) * split * warps


def solve_instructions(sass: str, full: int, iterations: int, warps: int) -> int | None:
    """The warp instructions a robot's solve program issues, from its machine code ``sass``: the
    code outside the loops once, the loop over the preparation's ``full`` row blocks (where ptxas
    kept one: the outermost loops but the last) ``full`` times, the last outermost loop (the
    iterations) ``iterations`` times and a loop inside it (the looped product's blocks) ``full``
    times an iteration, times the program's ``warps``; None if the code has another shape."""
    loops = loop_tree(sass)
    outer = [i for i, lp in enumerate(loops) if lp["parent"] is None]
    if not outer or len(outer) > 2 or any(lp["parent"] not in (None, outer[-1]) for lp in loops):
        return None
    trips = {i: full for i in range(len(loops))} | {outer[-1]: iterations}
    return issued(sass, loops, trips) * warps


def machine_code(dump: str, name: str, arch: str) -> str:
    """``nvdisasm -c`` of the kernel ``name`` whose PTX XLA dumped into ``dump``, assembled by ptxas."""
    ptx = next(f for f in Path(dump).glob("*.ptx") if name in f.read_text())
    cubin = Path(dump) / f"{name}.cubin"
    subprocess.run([tool("ptxas"), f"-arch={arch}", "-O3", str(ptx), "-o", str(cubin)], check=True)
    return subprocess.run([tool("nvdisasm"), "-c", str(cubin)], check=True, capture_output=True, text=True).stdout


def compiled_kernel(function, specs, name: str, arch: str, sharding, dump: str) -> tuple[str, dict]:
    """The kernel ``name`` of the jitted ``function`` compiled afresh for the abstract arguments
    ``specs`` on the deviceless GPU ``sharding`` (JAX's caches cleared, ``dump`` emptied first):
    its machine code (:func:`machine_code`) and ptxas' report of it (registers, spills; ``{}``
    where ptxas reported none)."""
    import jax

    from softcrawl.jaxsim.cost import captured_stderr, ptxas_report

    jax.clear_caches()
    shutil.rmtree(dump)  # this compilation's dump alone
    with captured_stderr() as log, jax.sharding.use_abstract_mesh(sharding.mesh.abstract_mesh):
        function.lower(*specs).compile()
    return machine_code(dump, name, arch), ptxas_report(log[0]).get(name, {})


def rid_variants(args, arch, sharding, dump) -> None:
    """``--kernel rid`` (module doc): one JSON line a variant."""
    import jax
    import jax.numpy as jnp

    from softcrawl.codesign.config import preset
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.jaxsim import legs, ridkernel
    from softcrawl.jaxsim.tables import build_table

    cfg = preset("paper")
    table = build_table(cfg.env.design_space(), factory=robot_factory(cfg), n_slots=6)
    part = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating)
                        else jnp.asarray(a), table.parts.leg)
    c = table.parts.settings.dt + table.parts.settings.rayleigh_stiffness
    families = [f.conn.shape for f in part.families]
    specs = [jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=sharding), part)] + [
        jax.ShapeDtypeStruct((576, part.mass.shape[0]), jnp.float32, sharding=sharding)] * 2
    for text in args.variants.split(","):
        elements, warps, dot, split, *more = text.split(":")
        ridkernel.ELEMENTS, ridkernel.NUM_WARPS, ridkernel.SPLIT = int(elements), int(warps), int(split)
        ridkernel.DOT_ALGORITHM = None if dot == "-" else dot
        ridkernel.ROW_GROUPS, ridkernel.TILE = ([*map(int, more)] + [1, 16][len(more):])[:2]  # defaults 1, 16
        terms = jax.jit(jax.vmap(lambda p, q, qd: legs.rid_terms(p, q, qd, c, "kernel"), in_axes=(None, 0, 0)))
        sass, report = compiled_kernel(terms, specs, "rid_terms", arch, sharding, dump)
        print(json.dumps({"kernel": "rid", "variant": {"elements": ridkernel.ELEMENTS, "num_warps": ridkernel.NUM_WARPS,
                                                       "dot_algorithm": ridkernel.DOT_ALGORITHM,
                                                       "split": ridkernel.SPLIT, "row_groups": ridkernel.ROW_GROUPS,
                                                       "tile": ridkernel.TILE},
                          "families": families, "arch": arch, "jax": jax.__version__, **report,
                          "warp_instructions_per_leg": leg_instructions(sass, families, ridkernel.ELEMENTS,
                                                                        ridkernel.SPLIT, ridkernel.NUM_WARPS),
                          "loops": [{"parent": lp["parent"], "total": lp["total"],
                                     "opcodes": dict(lp["opcodes"].most_common(12))} for lp in loop_tree(sass)]}),
              flush=True)


def factor_variants(args, arch, sharding, dump) -> None:
    """``--kernel factor`` (module doc): one JSON line a variant and kernel."""
    import jax
    import jax.numpy as jnp

    from softcrawl.jaxsim import factor

    def spec(*shape, dtype=jnp.float32):
        return jax.ShapeDtypeStruct(shape, dtype, sharding=sharding)

    def step(M, K, f_s, slots, f, w, x):  # a leg's step matrix and free motion, as the step forms them
        return factor.step_solve(M, K, f_s, slots, f, w, x, 1.0, 1.0, 0.01, 0.1, "kernel")

    kernels = (("step_solve", jax.vmap(step, in_axes=(None, 0, 0, None, 0, 0, 0)),  # 96 robots' matrices
                (spec(36, 36), spec(576, 33, 33), spec(576, 33), spec(36, dtype=jnp.int32), spec(576, 36),
                 spec(576, dtype=jnp.bool_), spec(576, 36)), 36),
               ("inverse_spd", jax.vmap(partial(factor.inverse_spd, form="kernel")), (spec(96, 72, 72),), 72))
    for text in args.variants.split(","):
        unroll, per = text.split(":")
        factor.UNROLL_PIVOTS, factor.PER_THREAD = int(unroll), int(per)
        for name, function, specs, n in kernels:
            sass, report = compiled_kernel(jax.jit(function), list(specs), name, arch, sharding, dump)
            loops = loop_tree(sass)
            outer = [i for i, lp in enumerate(loops) if lp["parent"] is None]
            total = len(_SASS.findall(sass))
            pivots = [min(size, n - start) for start, size in factor.row_parts(n)]
            if len(outer) > len(pivots):
                raise SystemExit(f"{name}: {len(outer)} outermost loops for {len(pivots)} blocks of pivots")
            # a loop over each block's pivots, but ptxas unrolls a short one (the last block's few) and
            # UNROLL_PIVOTS all: the loops are the first blocks', the rest straight-line code
            per_matrix = issued(sass, loops, dict(zip(outer, pivots)))
            warps = factor._warps(n)
            print(json.dumps({"kernel": name, "n": n, "variant": {"unroll_pivots": factor.UNROLL_PIVOTS,
                                                                  "per_thread": factor.PER_THREAD, "warps": warps},
                              "arch": arch, "jax": jax.__version__, **report, "blocks": factor.row_parts(n),
                              "instructions": total, "instructions_per_pivot": round(per_matrix / n, 1),
                              "warp_instructions_per_matrix": per_matrix * warps}), flush=True)


def elimination_variants(args, arch, sharding, dump) -> None:
    """``--kernel elimination`` (module doc): one JSON line a variant."""
    import jax
    import jax.numpy as jnp

    from softcrawl.jaxsim import elimination
    from softcrawl.jaxsim.factor import padded_size

    B, L, F3, Kd3, Kl3 = 96, 6, 12, 24, 36
    n = Kd3 + L * Kl3
    shapes = (((L * F3, L * F3), jnp.float32), ((L * F3, Kd3), jnp.float32), ((L, F3 + Kl3, F3 + Kl3), jnp.float32),
              ((L * F3,), jnp.bool_), ((L * F3,), jnp.float32), ((n,), jnp.float32))
    specs = [jax.ShapeDtypeStruct((B, *s), d, sharding=sharding) for s, d in shapes]
    for text in args.variants.split(","):
        warps, rows, dot = text.split(":")
        elimination.NUM_WARPS, elimination.ROW_BLOCK = int(warps), int(rows)
        elimination.DOT_ALGORITHM = None if dot == "-" else dot
        sass, report = compiled_kernel(jax.jit(jax.vmap(elimination.by_kernel)), specs, "attachment_elimination",
                                       arch, sharding, dump)
        loops = loop_tree(sass)
        if [lp["parent"] for lp in loops] != [None, None]:
            raise SystemExit(f"attachment_elimination: {len(loops)} loops, not the legs' and the row blocks'")
        blocks = padded_size(n) // min(elimination.ROW_BLOCK, padded_size(n))
        print(json.dumps({"kernel": "elimination", "variant": {"num_warps": elimination.NUM_WARPS,
                                                               "row_block": elimination.ROW_BLOCK,
                                                               "dot_algorithm": elimination.DOT_ALGORITHM},
                          "arch": arch, "jax": jax.__version__, **report, "instructions": len(_SASS.findall(sass)),
                          "loops": [{"parent": lp["parent"], "total": lp["total"]} for lp in loops],
                          "warp_instructions_per_robot": issued(sass, loops, {0: L, 1: L * blocks})
                          * elimination.NUM_WARPS}), flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--gpu-target", default=str(Path(__file__).parent / "gpu_targets" / "h100.pbtxt"))
    p.add_argument("--kernel", choices=tuple(DEFAULT_VARIANTS), default="solve")
    p.add_argument("--variants", default=None,
                   help="comma-separated (- for None); solve: ROW_BLOCK:NUM_WARPS:LOOP_PRODUCT:RESIDENT_ROWS; rid: "
                        "ELEMENTS:NUM_WARPS:DOT_ALGORITHM:SPLIT[:ROW_GROUPS[:TILE]]; factor: UNROLL_PIVOTS:PER_THREAD; "
                        "elimination: NUM_WARPS:ROW_BLOCK:DOT_ALGORITHM; defaults: "
                        + "; ".join(f"{k} {v}" for k, v in DEFAULT_VARIANTS.items()))
    p.add_argument("--contacts", type=int, default=80, help="contact slots K (the operator is 3K x 3K)")
    p.add_argument("--schur", default=None, metavar="KD:L:KL",
                   help="the operator in its parts (softcrawl.jaxsim.schur.SchurOperator): KD disk contacts and "
                        "L legs of KL contacts (the paper preset's 8:6:12), instead of --contacts' dense operator")
    args = p.parse_args(argv)
    from softcrawl.jaxsim.cost import prepare_deviceless_gpu

    dump = tempfile.mkdtemp(prefix="kernel_sass_")
    # the emitters' PTX (JAX 0.11 dumps it only where an emitter is named)
    os.environ["XLA_FLAGS"] = (f"{os.environ.get('XLA_FLAGS', '')} --xla_dump_to={dump} --xla_dump_hlo_pass_re=NONE "
                               "--xla_dump_emitter_re=.*")
    prepare_deviceless_gpu(ptxas_report=True)
    import jax
    import jax.numpy as jnp

    from softcrawl.jaxsim import fused
    from softcrawl.jaxsim.cost import deviceless_gpu
    from softcrawl.jaxsim.gpu import target_capability
    from softcrawl.jaxsim.schur import SchurOperator

    config = Path(args.gpu_target).read_text()
    sharding = deviceless_gpu(config)
    major, minor = target_capability(config)
    arch = f"sm_{major}{minor}{'a' if major >= 9 else ''}"  # Triton's PTX targets sm_90a, sm_100a, sm_120a
    args.variants = args.variants or DEFAULT_VARIANTS[args.kernel]
    if args.kernel == "rid":
        return rid_variants(args, arch, sharding, dump)
    if args.kernel == "factor":
        return factor_variants(args, arch, sharding, dump)
    if args.kernel == "elimination":
        return elimination_variants(args, arch, sharding, dump)
    B = 256
    if args.schur:
        Kd, L, Kl = (int(v) for v in args.schur.split(":"))
        K = Kd + L * Kl
        n, nd, nl = 3 * K, 3 * Kd, 3 * Kl
        operator = SchurOperator(*(jax.ShapeDtypeStruct((B, *s), jnp.float32, sharding=sharding)
                                   for s in ((nd, nd), (L, nl + 12, nl + 12), (n, nd), (L, n, nl))))
    else:
        K = args.contacts
        n = 3 * K
        operator = jax.ShapeDtypeStruct((B, n, n), jnp.float32, sharding=sharding)
    shapes = (((B, n), jnp.float32), ((B, K), jnp.float32), ((B, n), jnp.float32), ((B, K), bool),
              ((48,), jnp.float32))
    specs = [operator] + [jax.ShapeDtypeStruct(s, d, sharding=sharding) for s, d in shapes]
    for text in args.variants.split(","):
        rows, warps, loop, held = text.split(":")
        fused.ROW_BLOCK, fused.NUM_WARPS, fused.LOOP_PRODUCT = int(rows), int(warps), loop == "1"
        fused.RESIDENT_ROWS = None if held == "-" else int(held)
        solve = jax.jit(jax.vmap(fused.fused_solve, in_axes=(0, 0, 0, 0, 0, None)))
        sass, report = compiled_kernel(solve, specs, "apgd_solve", arch, sharding, dump)
        *before, ops = outer_loops(sass)
        full = n // fused.program_rows(n, jnp.float32)[1]  # the preparation's full row blocks
        print(json.dumps({"variant": {"row_block": fused.ROW_BLOCK, "num_warps": fused.NUM_WARPS,
                                      "loop_product": fused.LOOP_PRODUCT, "resident_rows": fused.RESIDENT_ROWS},
                          "contacts": K, "operator": args.schur or "dense", "arch": arch, "jax": jax.__version__,
                          **report,
                          "loop_instructions": sum(ops.values()), "loop_opcodes": dict(ops.most_common()),
                          "warp_instructions_per_robot": solve_instructions(sass, full, 48, fused.NUM_WARPS),
                          "loops_before": [sum(c.values()) for c in before]}),
              flush=True)


if __name__ == "__main__":
    main()
