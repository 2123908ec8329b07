"""Robot-steps per second of the JAX engine (:mod:`softcrawl.jaxsim`) against batch size, on whatever
device JAX has (CPU or GPU). Prints one JSON line per batch size.

    python benchmarks/gpu_step.py [--precision fp32|fp64] [--batches 1,4,16,...,16384]
        [--max-batch 16384] [--steps 10] [--calls 5] [--designs 1,0,0,2,2,0,0,0;...]
        [--leg-contacts 12] [--disk-contacts 8] [--sweeps 100]

A batch holds copies of the given designs in turn (mixed leg counts are padded to the most legs,
absent legs masked). The robots first land (50 steps at zero pressure), then every call of the
jitted rollout advances all of them ``--steps`` steps with regulators 1 and 2 commanded to 90 and
40 kPa; robot-steps/s = batch x steps x calls / wall seconds of the timed calls (compilation is
timed and reported separately). On the CPU keep ``--max-batch`` small: one robot step costs
milliseconds per core.
"""

from __future__ import annotations

import argparse
import json
import time


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--precision", choices=("fp32", "fp64"), default="fp32")
    ap.add_argument("--batches", default=",".join(str(4 ** k) for k in range(8)))
    ap.add_argument("--max-batch", type=int, default=16384)
    ap.add_argument("--steps", type=int, default=10, help="steps per jitted call")
    ap.add_argument("--calls", type=int, default=5, help="timed calls per batch size")
    ap.add_argument("--designs", default="1,0,0,2,2,0,0,0", help="';'-separated designs")
    ap.add_argument("--leg-contacts", type=int, default=12)
    ap.add_argument("--disk-contacts", type=int, default=8)
    ap.add_argument("--sweeps", type=int, default=100)
    args = ap.parse_args(argv)

    import jax

    if args.precision == "fp64":
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from softcrawl.jaxsim.engine import Control, make_rollout, rest_state
    from softcrawl.jaxsim.model import build_model, select_robots
    from softcrawl.robot import RobotConfig, build_robot

    robots = [build_robot(d, RobotConfig(model="reduced")) for d in args.designs.split(";")]
    base = build_model(robots, leg_contacts=args.leg_contacts, disk_contacts=args.disk_contacts, sweeps=args.sweeps)
    land, roll = make_rollout(50), make_rollout(args.steps)
    for B in (int(b) for b in args.batches.split(",")):
        if B > args.max_batch:
            continue
        model = select_robots(base, jnp.arange(B) % len(robots))
        dt = base.disk.rest.dtype
        state = rest_state(model)
        zero = Control(jnp.zeros((B, 3), dt))
        go = Control(jnp.tile(jnp.asarray([90.0, 40.0, 0.0], dt), (B, 1)))
        t0 = time.perf_counter()
        state = jax.block_until_ready(land(model, state, zero))
        land_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        state = jax.block_until_ready(roll(model, state, go))
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(args.calls):
            state = roll(model, state, go)
        jax.block_until_ready(state)
        wall = time.perf_counter() - t0
        print(json.dumps({"device": str(jax.devices()[0]), "precision": args.precision, "batch": B,
                          "designs": args.designs, "steps_per_call": args.steps, "land_and_compile_s": land_s,
                          "first_call_s": compile_s, "robot_steps_per_s": B * args.steps * args.calls / wall,
                          "bad_robots": int((state.bad > 0).sum())}), flush=True)


if __name__ == "__main__":
    main()
