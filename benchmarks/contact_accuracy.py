"""How well the JAX engine's contact solve solves the contact problems of landed, pressurised robots:
the default solve (accelerated projected gradient without restart, its default iterations,
:func:`softcrawl.jaxsim.contact.solve_contacts`) against the previous engine's projected
Gauss-Seidel (100 sweeps), on the same problems with the same warm start; ``apgd_float16``: the
default solve reading the Delassus operator in float16 (``Settings.delassus = "dense16"``; the
float32 engine's default ``"fused16"`` is the same solve in one GPU kernel; ``apgd`` reads it in
the arrays' precision).

Random designs of the ``paper`` preset (each leg count of the space in turn) are settled
(:func:`~softcrawl.jaxsim.engine.make_settle`), then held for one action at random regulator
commands on the default engine; at every ``--every``-th step of that action the problem the
next step solves (:func:`~softcrawl.jaxsim.engine.contact_problem`) is solved by each solver
and by a converged reference (the adaptive-restart gradient, ``--reference`` iterations).
Per solver: the median and 90th percentile over the problems of the largest penetration
velocity ``max(-u_n, 0)`` over the active contacts (mm/s; at dt 0.02 s, 1 mm/s is 0.02 mm of
penetration per step, which the next step's gap term corrects) and of the largest constraint
velocity error against the reference (mm/s). Prints one JSON object.

Usage: python benchmarks/contact_accuracy.py [--designs 12] [--every 5] [--precision float32]
       [--reference 4000] [--seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--designs", type=int, default=12)
    p.add_argument("--every", type=int, default=5, help="record every k-th step of the pressurised action")
    p.add_argument("--precision", choices=("float32", "float64"), default="float32")
    p.add_argument("--reference", type=int, default=4000, help="iterations of the converged reference")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", args.precision == "float64")
    import jax.numpy as jnp
    import numpy as np

    from softcrawl.codesign.config import preset
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.jaxsim import contact
    from softcrawl.jaxsim.engine import contact_problem, make_settle, rest_state
    from softcrawl.jaxsim.rig import Rig, make_action_rollout
    from softcrawl.jaxsim.tables import build_table

    cfg = preset("paper")
    space = cfg.env.design_space()
    rng = np.random.default_rng(args.seed)
    counts = list(range(space.min_legs, space.max_legs + 1))
    pools = {n: [d for d in space.canonical_designs if sum(v > 0 for v in d) == n] for n in counts}
    designs = [pools[counts[i % len(counts)]][rng.integers(len(pools[counts[i % len(counts)]]))]
               for i in range(args.designs)]
    table = build_table(space, factory=robot_factory(cfg), n_slots=space.max_legs)
    model = table.model(designs)
    B, R, steps = len(designs), space.n_regulators, cfg.env.steps_per_action
    state, _ = make_settle()(model, rest_state(model))
    dt = state.x.dtype
    rig = Rig(jnp.ones((B, R), dt), jnp.zeros((B, R), dt), jnp.zeros((B, R), dt), jnp.zeros((B, R), dt))
    command = jnp.asarray(rng.uniform(30.0, 90.0, (B, R)), dt)
    roll = make_action_rollout(args.every)
    problem = jax.jit(jax.vmap(lambda rd, s, kpa: contact_problem(dataclasses.replace(model, robot=rd), s, kpa)))
    solvers = {
        "apgd": jax.jit(jax.vmap(lambda *a: contact.solve_contacts(*a, "apgd", contact.DEFAULT_ITERATIONS["apgd"]))),
        "apgd_float16": jax.jit(jax.vmap(lambda *a: contact.solve_contacts(*a, "apgd", contact.DEFAULT_ITERATIONS["apgd"],
                                                                           storage="float16"))),
        "pgs": jax.jit(jax.vmap(lambda *a: contact.solve_contacts(*a, "pgs", 100))),
        "reference": jax.jit(jax.vmap(lambda *a: contact.apgd_coulomb(*a, args.reference))),
    }
    residual = jax.jit(jax.vmap(contact.residuals))
    pen = {k: [] for k in solvers}
    err = {k: [] for k in solvers if k != "reference"}
    warp = model.settings.calibration
    for _ in range(steps // args.every):
        state, _ = roll(model, rig, state, command, jnp.full((B,), args.every, jnp.int32))
        sim = jnp.maximum(warp[0] * state.pressure + warp[1], 0.0)
        W, q, mu, warm, active = problem(model.robot, state, sim)
        lams = {k: f(W, q, mu, warm, active) for k, f in solvers.items()}
        u_ref = jnp.einsum("bij,bj->bi", W, lams["reference"]) + q
        for k, lam in lams.items():
            pen[k] += np.asarray(residual(W, q, mu, lam, active)["penetration"], float).tolist()
            if k in err:
                u = jnp.einsum("bij,bj->bi", W, lam) + q
                live = jnp.repeat(active, 3, axis=1)
                err[k] += np.asarray(jnp.max(jnp.where(live, jnp.abs(u - u_ref), 0), axis=1), float).tolist()

    def stats(v):
        return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(np.max(v))}

    print(json.dumps({"host": platform.node(), "device": str(jax.devices()[0]), "precision": args.precision,
                      "designs": [",".join(map(str, d)) for d in designs], "problems": len(pen["apgd"]),
                      "apgd_iterations": contact.DEFAULT_ITERATIONS["apgd"], "pgs_sweeps": 100,
                      "penetration_mm_s": {k: stats(v) for k, v in pen.items()},
                      "velocity_error_mm_s": {k: stats(v) for k, v in err.items()}}))


if __name__ == "__main__":
    main()
