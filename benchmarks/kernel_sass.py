"""The contact solve kernel's iteration read from its machine code, without a GPU.

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
the float16 conversions). A proxy for time where no GPU is lent, not a measurement.

Needs JAX's CUDA plugin of the installed JAX's version and ``nvdisasm`` (``pip install
"jax-cuda12-plugin[with-cuda]==<jax version>" nvidia-cuda-nvdisasm``).

Usage:
    python benchmarks/kernel_sass.py [--gpu-target benchmarks/gpu_targets/h100.pbtxt]
        [--variants 64:8:0:-,64:8:0:128] [--contacts 80 | --schur 8:6:12]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import subprocess
import tempfile
from pathlib import Path

_SASS = re.compile(r"^\s*/\*([0-9a-f]{4,})\*/\s+(.*?);", re.M)
_LABEL = re.compile(r"^\s*\.(L_x_\d+):\s*\n(?:.*\n)*?\s*/\*([0-9a-f]{4,})\*/", re.M)


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


def outer_loops(sass: str) -> list[collections.Counter]:
    """The opcodes (predicates and modifiers dropped) of each outermost loop of ``nvdisasm -c``
    output, in the order of the code (a loop: the instructions from a label to the furthest
    backward branch to it; outermost: inside no other). In the solve kernel the last is the
    iterations: they follow the loop that prepares the operator."""
    ins = [(int(a, 16), t) for a, t in _SASS.findall(sass)]
    labels = {m.group(1): int(m.group(2), 16) for m in _LABEL.finditer(sass)}
    loops = {}
    for a, t in ins:
        m = re.search(r"BRA\s+`?\(?\.?(L_x_\d+)", t)
        if m and labels.get(m.group(1), a) < a:
            loops[labels[m.group(1)]] = max(a, loops.get(labels[m.group(1)], a))
    outer = [(s, e) for s, e in loops.items() if not any(s2 <= s and e <= e2 and (s2, e2) != (s, e)
                                                         for s2, e2 in loops.items())]
    return [collections.Counter(re.sub(r"^@!?U?P\w+\s+", "", t).split()[0].split(".")[0]
                                for a, t in ins if start <= a <= end) for start, end in sorted(outer)]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--gpu-target", default=str(Path(__file__).parent / "gpu_targets" / "h100.pbtxt"))
    p.add_argument("--variants", default="64:8:0:-,64:8:0:128,64:8:0:64",
                   help="ROW_BLOCK:NUM_WARPS:LOOP_PRODUCT:RESIDENT_ROWS (- for None), comma-separated")
    p.add_argument("--contacts", type=int, default=80, help="contact slots K (the operator is 3K x 3K)")
    p.add_argument("--schur", default=None, metavar="KD:L:KL",
                   help="the operator in its parts (softcrawl.jaxsim.schur.SchurOperator): KD disk contacts and "
                        "L legs of KL contacts (the paper preset's 8:6:12), instead of --contacts' dense operator")
    args = p.parse_args(argv)
    from softcrawl.jaxsim.cost import captured_stderr, prepare_deviceless_gpu, ptxas_report

    dump = tempfile.mkdtemp(prefix="kernel_sass_")
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_dump_to={dump} --xla_dump_hlo_pass_re=NONE"
    prepare_deviceless_gpu(ptxas_report=True)
    import jax
    import jax.numpy as jnp

    from softcrawl.jaxsim import fused
    from softcrawl.jaxsim.cost import deviceless_gpu
    from softcrawl.jaxsim.schur import SchurOperator

    config = Path(args.gpu_target).read_text()
    sharding = deviceless_gpu(config)
    cc = re.search(r"cuda_compute_capability\s*{\s*major:\s*(\d+)(?:\s*minor:\s*(\d+))?", config)
    arch = f"sm_{cc.group(1)}{cc.group(2) or 0}{'a' if cc.group(1) == '9' else ''}"
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
        jax.clear_caches()
        for f in Path(dump).iterdir():
            f.unlink()
        solve = jax.jit(jax.vmap(fused.fused_solve, in_axes=(0, 0, 0, 0, 0, None)))
        with captured_stderr() as log, jax.sharding.use_abstract_mesh(sharding.mesh.abstract_mesh):
            solve.lower(*specs).compile()
        report = ptxas_report(log[0]).get("apgd_solve", {})
        ptx = next(f for f in Path(dump).glob("*.ptx") if "apgd_solve" in f.read_text())
        cubin = Path(dump) / "solve.cubin"
        subprocess.run([tool("ptxas"), f"-arch={arch}", "-O3", str(ptx), "-o", str(cubin)], check=True)
        *before, ops = outer_loops(subprocess.run([tool("nvdisasm"), "-c", str(cubin)], check=True, capture_output=True,
                                          text=True).stdout)
        print(json.dumps({"variant": {"row_block": fused.ROW_BLOCK, "num_warps": fused.NUM_WARPS,
                                      "loop_product": fused.LOOP_PRODUCT, "resident_rows": fused.RESIDENT_ROWS},
                          "contacts": K, "operator": args.schur or "dense", "arch": arch, "jax": jax.__version__,
                          **report,
                          "loop_instructions": sum(ops.values()), "loop_opcodes": dict(ops.most_common()),
                          "loops_before": [sum(c.values()) for c in before]}),
              flush=True)


if __name__ == "__main__":
    main()
