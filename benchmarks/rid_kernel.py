"""The legs' RID terms in one kernel (``Settings.rid_form = "kernel"``, :mod:`softcrawl.jaxsim.ridkernel`)
against XLA's forms (``"pairs"``, a GPU's default, and ``"rows"``), on JAX's default device.

On the `paper` preset's shipped leg (239 tetrahedra, 170 membrane triangles, 33 strain modes) at
random modal states (``--amplitude`` mm of displacement, 50 times that in mm/s of velocity),
float32, printed as JSON lines:

* ``"part": "agreement"``: each form's largest error in ``K_r`` and ``f_r`` against the rows
  form in float64, relative to their largest entries, and the bad elements each counts; the kernel
  compiled for the GPU (or run in Pallas' interpreter where JAX has none);
* ``"part": "time"``: ``ms`` per call of each form at each of ``--robots`` (a call treats
  ``--legs`` legs per robot), the rows form only where its ``Z`` fits (``--rows-max`` robots), and
  on a GPU the kernel's variants (``ELEMENTS``, ``NUM_WARPS``, ``DOT_ALGORITHM``, ``SPLIT``,
  ``ROW_GROUPS``, ``TILE``).

Usage:
    python benchmarks/rid_kernel.py [--robots 96,16384] [--legs 6] [--calls 20]
"""

from __future__ import annotations

import argparse
import json
import time
from functools import partial

#: The kernel's variants timed on a GPU: (ELEMENTS, NUM_WARPS, DOT_ALGORITHM, SPLIT, ROW_GROUPS,
#: TILE). Three row groups hold 168 registers a thread instead of 254 (six programs a
#: multiprocessor instead of four) for 15% more instructions; one warp in three row groups issues
#: 11% fewer instructions than the default, without barriers, in programs twice as long, so two of
#: them a leg as well (``kernel_sass.py --kernel rid``).
VARIANTS = ((16, 2, "SPLIT_TF32", 1, 1, 16), (16, 2, "SPLIT_BF16", 2, 1, 16), (16, 2, "TF32_TF32_F32_X3", 1, 1, 16),
            (16, 4, "SPLIT_BF16", 1, 1, 16), (16, 2, "F32_F32_F32", 1, 1, 16), (16, 2, "SPLIT_BF16", 1, 1, 32),
            (16, 2, "SPLIT_BF16", 1, 3, 16), (16, 1, "SPLIT_BF16", 1, 3, 16), (16, 1, "SPLIT_BF16", 2, 3, 16))
NAMES = ("ELEMENTS", "NUM_WARPS", "DOT_ALGORITHM", "SPLIT", "ROW_GROUPS", "TILE")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", default="96,16384", help="robots per call at which the forms are timed")
    p.add_argument("--legs", type=int, default=6)
    p.add_argument("--amplitude", type=float, default=0.5, help="modal displacements' scale, mm")
    p.add_argument("--rows-max", type=int, default=1024, help="largest robot count the rows form is timed at")
    p.add_argument("--calls", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from softcrawl.codesign.config import preset
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.jaxsim import legs, ridkernel
    from softcrawl.jaxsim.tables import build_table

    device = jax.devices()[0]
    gpu = device.platform == "gpu"
    kernel = "kernel" if gpu else "interpret"
    cfg = preset("paper")
    table = build_table(cfg.env.design_space(), factory=robot_factory(cfg), n_slots=args.legs)
    part64 = table.parts.leg
    c = table.parts.settings.dt + table.parts.settings.rayleigh_stiffness

    def cast(tree, dtype):
        return jax.tree.map(lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating)
                            else jnp.asarray(a), tree)

    part = cast(part64, jnp.float32)
    m = part.mass.shape[0]
    rng = np.random.default_rng(args.seed)
    head = {"device": f"{device.platform}:{device.device_kind}", "jax": jax.__version__, "amplitude": args.amplitude}

    def batched(form, p):  # the part an argument: a constant would be folded at compile time
        f = jax.jit(jax.vmap(lambda p, q, qd: legs.rid_terms(p, q, qd, c, form), in_axes=(None, 0, 0)))
        return partial(f, p)

    def state(n, dtype):
        q = args.amplitude * rng.standard_normal((n, m))
        return jnp.asarray(q, dtype), jnp.asarray(50 * q, dtype)

    q, qd = state(16, jnp.float64)
    K0, f0, _ = batched("rows", part64)(q, qd)
    K0, f0 = np.asarray(K0), np.asarray(f0)
    q32, qd32 = q.astype(jnp.float32), qd.astype(jnp.float32)
    out = {**head, "part": "agreement", "kernel": kernel}
    for form in ("rows", "pairs", kernel):
        K, f, bad = batched(form, part)(q32, qd32)
        out[form] = {"K": float(np.abs(np.asarray(K, float) - K0).max() / np.abs(K0).max()),
                     "f": float(np.abs(np.asarray(f, float) - f0).max() / np.abs(f0).max()),
                     "bad": int(np.asarray(bad).sum())}
    print(json.dumps(out), flush=True)
    default = tuple(getattr(ridkernel, name) for name in NAMES)
    for robots in (int(b) for b in args.robots.split(",")):
        q, qd = state(robots * args.legs, jnp.float32)

        def timed(f):
            jax.block_until_ready(f(q, qd))
            t0 = time.perf_counter()
            for _ in range(args.calls):
                r = f(q, qd)
            jax.block_until_ready(r)
            return 1e3 * (time.perf_counter() - t0) / args.calls

        out = {**head, "part": "time", "robots": robots, "legs": robots * args.legs}
        shared = {"pairs": jax.jit(legs.with_frame_stiffness)(part), "rows": part}  # as a loop of steps has them
        for form in ("pairs", "rows") if robots <= args.rows_max else ("pairs",):
            out[f"{form}_ms"] = timed(batched(form, shared[form]))
        for variant in dict.fromkeys((default, *VARIANTS)) if gpu else (default,):
            for name, value in zip(NAMES, variant):
                setattr(ridkernel, name, value)
            jax.clear_caches()
            rows = jax.jit(ridkernel.with_kernel_rows)(part)  # as the variant's tiles read them
            out["kernel_ms_" + "_".join(map(str, variant))] = timed(batched(kernel, rows))
        for name, value in zip(NAMES, default):
            setattr(ridkernel, name, value)
        jax.clear_caches()
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
