"""The contact solve's iterations in one kernel (``Settings.delassus = "fused16"``,
:mod:`softcrawl.jaxsim.fused`) against XLA's iterations (``"dense16"``), on JAX's default device.

For a batch of the preset's designs (as ``step_cost.py``) landed for one action, printed as JSON
lines:

* ``"part": "agreement"``: their contact problems (:func:`softcrawl.jaxsim.engine.contact_problem`)
  solved by 48 iterations from the engine's warm start in both forms, the kernel compiled for the
  GPU (or run in Pallas' interpreter where JAX has none): the largest impulse difference relative
  to the robot's largest impulse, and of the constraint velocities ``W lam`` (mm/s);
* ``"part": "rollout"`` (GPU only: on a CPU ``"fused16"`` steps as ``"dense"``): ``--actions``
  actions of the whole engine from the landed state in each form, the disk nodes' largest
  distance between the two (mm) and the robots that went invalid;
* ``"part": "solve"``: the solve alone (the problems tiled to each of ``--batches``),
  ``ms_per_solve`` of XLA's iterations and of the kernel (on a GPU also its variants: rows of
  the operator multiplied at once, warps, the product looped or unrolled and the operator held on
  chip, :data:`softcrawl.jaxsim.fused.ROW_BLOCK`, :data:`~softcrawl.jaxsim.fused.NUM_WARPS`,
  :data:`~softcrawl.jaxsim.fused.LOOP_PRODUCT`, :data:`~softcrawl.jaxsim.fused.RESIDENT_ROWS`, none
  spilling on an H100).

``--resident-rows`` sets :data:`~softcrawl.jaxsim.fused.RESIDENT_ROWS` for the agreement and
rollout parts and makes it the first of the variants.

Usage:
    python benchmarks/fused_kernel.py [--preset paper] [--batch 96] [--batches 96,16384] [--actions 3]
        [--resident-rows 128]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--batch", type=int, default=96, help="robots landed and compared")
    p.add_argument("--batches", default="96,16384", help="batch sizes at which the solve alone is timed")
    p.add_argument("--calls", type=int, default=20, help="timed calls per batch size")
    p.add_argument("--actions", type=int, default=3, help="actions rolled out in each form (GPU only; 0: none)")
    p.add_argument("--resident-rows", type=int, default=None, metavar="ROWS",
                   help="the kernel compared holds the operator on chip by blocks of ROWS rows")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    import jax
    import jax.numpy as jnp
    import numpy as np

    from softcrawl.codesign.config import preset
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.jaxsim import fused as fused_mod
    from softcrawl.jaxsim.contact import DEFAULT_ITERATIONS, solve_contacts
    from softcrawl.jaxsim.engine import contact_problem, rest_state
    from softcrawl.jaxsim.rig import Rig, make_action_rollout, rig_pressures
    from softcrawl.jaxsim.tables import build_table

    device = jax.devices()[0]
    gpu = device.platform == "gpu"
    cfg = preset(args.preset)
    space, designs = cfg.env.design_space(), cfg.env.designs()
    slots = max(sum(v > 0 for v in d) for d in designs)
    table = build_table(space, factory=robot_factory(cfg), n_slots=slots, delassus="dense16")
    rng = np.random.default_rng(args.seed)
    B, R, steps = args.batch, space.n_regulators, cfg.env.steps_per_action
    model = table.model([designs[i] for i in rng.integers(len(designs), size=B)])
    dt = model.disk.rest.dtype
    rig = Rig(jnp.ones((B, R), dt), jnp.zeros((B, R), dt), jnp.zeros((B, R), dt), jnp.zeros((B, R), dt))
    steps_b = jnp.full((B,), steps, jnp.int32)
    go = jnp.tile(jnp.asarray(np.linspace(90.0, 30.0, R), dt), (B, 1))
    roll = make_action_rollout(steps)  # one jitted program per settings: the landing's is dense16's
    state, _ = roll(model, rig, rest_state(model), go, steps_b)
    head = {"preset": args.preset, "device": f"{device.platform}:{device.device_kind}", "jax": jax.__version__,
            "robots": B, "iterations": DEFAULT_ITERATIONS["apgd"]}

    def one(rd, s, rg):  # the next step's problem at the regulators' present pressures
        mdl = dataclasses.replace(model, robot=rd)
        return contact_problem(mdl, s, rig_pressures(mdl.settings, rg, s.pressure))

    problems = jax.jit(jax.vmap(one))(model.robot, state, rig)
    fused_mod.RESIDENT_ROWS = args.resident_rows
    head["resident_rows"] = args.resident_rows
    kernel = "gpu" if gpu else "interpret"

    def solver(fused):  # the engine's solve of a batch, XLA's iterations (None) or the kernel's
        return jax.jit(jax.vmap(lambda *a: solve_contacts(*a, "apgd", DEFAULT_ITERATIONS["apgd"], storage="float16",
                                                          fused=fused)))

    solvers = {"dense16": solver(None), "fused16": solver(kernel)}
    xla, fused = (np.asarray(solvers[f](*problems), float) for f in ("dense16", "fused16"))
    W = np.asarray(problems[0], float)
    scale = np.maximum(np.abs(xla).max(axis=1), 1e-30)
    print(json.dumps({**head, "part": "agreement", "kernel": kernel,
                      "max_rel_impulse_diff": float((np.abs(fused - xla).max(axis=1) / scale).max()),
                      "max_velocity_diff_mm_s": float(np.abs(np.einsum("bij,bj->bi", W, fused - xla)).max()),
                      "velocity_scale_mm_s": float(np.abs(np.einsum("bij,bj->bi", W, xla)).max())}), flush=True)
    default = (fused_mod.ROW_BLOCK, fused_mod.NUM_WARPS, fused_mod.LOOP_PRODUCT, fused_mod.RESIDENT_ROWS)
    if gpu and args.actions:  # on a CPU "fused16" steps as "dense": nothing to compare
        ends = {}
        for form in ("dense16", "fused16"):
            mdl = dataclasses.replace(model, settings=dataclasses.replace(model.settings, delassus=form))
            s, dead = state, jnp.zeros(B, bool)
            for _ in range(args.actions):
                s, d = roll(mdl, rig, s, go, steps_b)
                dead = dead | d
            ends[form] = (np.asarray(s.x), int(np.sum(np.asarray(dead))))
        gap = np.linalg.norm(ends["fused16"][0] - ends["dense16"][0], axis=-1).max()
        print(json.dumps({**head, "part": "rollout", "actions": args.actions, "max_node_distance_mm": float(gap),
                          "bad_robots": {f: e[1] for f, e in ends.items()}}), flush=True)
    variants = [default] + [v for v in ((64, 8, False, None), (16, 8, False, None), (16, 16, False, None),  # none
                                        (32, 4, False, None), (32, 8, True, None), (16, 8, True, None),  # spills on
                                        (64, 8, False, 128), (64, 8, False, 64)) if v != default]  # an H100
    for nb in (int(b) for b in args.batches.split(",")):
        tiled = jax.tree_util.tree_map(lambda a: jnp.asarray(np.resize(np.asarray(a), (nb, *a.shape[1:]))), problems)
        out = {**head, "part": "solve", "batch": nb}

        def timed(solve):
            jax.block_until_ready(solve(*tiled))
            t0 = time.perf_counter()
            for _ in range(args.calls):
                r = solve(*tiled)
            jax.block_until_ready(r)
            return 1e3 * (time.perf_counter() - t0) / args.calls

        out["dense16_ms_per_solve"] = timed(solvers["dense16"])
        for v in variants if gpu else variants[:1]:  # the kernel's variants (module constants)
            rows, warps, loop, held = v
            fused_mod.ROW_BLOCK, fused_mod.NUM_WARPS, fused_mod.LOOP_PRODUCT, fused_mod.RESIDENT_ROWS = v
            jax.clear_caches()
            name = f"held{held}" if held else f"rows{rows}{'_looped' if loop else ''}"
            out[f"fused16_{name}_w{warps}_ms_per_solve"] = timed(solver(kernel))
        fused_mod.ROW_BLOCK, fused_mod.NUM_WARPS, fused_mod.LOOP_PRODUCT, fused_mod.RESIDENT_ROWS = default
        jax.clear_caches()
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
