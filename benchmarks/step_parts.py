"""Where the JAX engine's physics step spends its time: each part of one step of a batch of the
``paper`` preset's robots (landed and pressed first), jitted and timed alone, on JAX's default
device. Prints one JSON line per part:

* ``physics_step``: the whole step (:func:`softcrawl.jaxsim.engine.physics_step`);
* ``constrained``: the free motion, constraint rows and condensed contact problem;
* ``free_motion``: the legs' free motion (RID terms, cavity load, Cholesky step);
* ``rid_terms_rows`` / ``rid_terms_pairs``: the legs' RID terms in both orders of the sums
  (:func:`softcrawl.jaxsim.legs.rid_terms`; the engine takes ``rows`` on a CPU, ``pairs`` elsewhere);
* ``solve_contacts``: the contact solve alone (its default solver and iterations).

Each is ``ms`` per call (the mean of ``--calls`` calls after a first, compiling one). The parts
overlap (a part's time includes the parts inside it). Figures: benchmarks/RESULTS.md.

    python benchmarks/step_parts.py [--batch 1024] [--precision float32|float64] [--calls 10]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--precision", choices=("float32", "float64"), default="float32")
    p.add_argument("--calls", type=int, default=10)
    args = p.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", args.precision == "float64")
    import jax.numpy as jnp
    import numpy as np

    from softcrawl.codesign.config import preset
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.jaxsim import engine, legs
    from softcrawl.jaxsim.contact import solve_contacts
    from softcrawl.jaxsim.tables import build_table

    cfg = preset("paper")
    space, designs = cfg.env.design_space(), cfg.env.designs()
    table = build_table(space, factory=robot_factory(cfg), n_slots=6)
    B, R = args.batch, space.n_regulators
    model = table.model([designs[i] for i in np.random.default_rng(0).integers(len(designs), size=B)])
    state = engine.rest_state(model)
    kpa = jnp.tile(jnp.linspace(30.0, 10.0, R, dtype=state.x.dtype), (B, 1))
    roll = engine.make_rollout(50, physics_only=True)
    state = roll(model, roll(model, state, 0.0 * kpa), kpa)  # landed, then pressed
    device = jax.devices()[0]

    def per_robot(f):
        def one(m, rd, s, p):
            with jax.default_matmul_precision("float32"):
                return f(dataclasses.replace(m, robot=rd), s, p)
        return jax.jit(lambda m, s, p: jax.vmap(one, in_axes=(None, 0, 0, 0))(
            dataclasses.replace(m, robot=None), m.robot, s, p))

    def report(name, f, *a):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*a))
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(args.calls):
            out = f(*a)
        jax.block_until_ready(out)
        print(json.dumps({"part": name, "batch": B, "ms": 1e3 * (time.perf_counter() - t0) / args.calls,
                          "first_call_s": round(first, 2), "precision": args.precision,
                          "device": f"{device.platform}:{device.device_kind}"}), flush=True)

    def free_motion(m, s, p):
        rd = m.robot
        return jax.vmap(legs.free_motion, in_axes=(None, None, 0, 0, 0, 0, 0))(
            m.leg, m.settings, s.q, s.qdot, rd.rotation, p[rd.channel] * rd.leg_mask, rd.leg_mask)[:2]

    def rid(form):
        return lambda m, s, p: jax.vmap(legs.rid_terms, in_axes=(None, 0, 0, None, None))(
            m.leg, s.q, s.qdot, m.settings.dt + m.settings.rayleigh_stiffness, form)[:2]

    def problem(m, s, p):
        *_, rows, cond, warm = engine._constrained(m, s, p)
        return cond.W, cond.q, warm, rows.active

    st = model.settings
    report("physics_step", per_robot(engine.physics_step), model, state, kpa)
    report("constrained", per_robot(lambda m, s, p: engine._constrained(m, s, p)[6]), model, state, kpa)
    report("free_motion", per_robot(free_motion), model, state, kpa)
    for form in ("rows", "pairs"):
        report(f"rid_terms_{form}", per_robot(rid(form)), model, state, kpa)
    solve = jax.jit(jax.vmap(lambda W, q, warm, active: solve_contacts(
        W, q, jnp.full(active.shape, st.friction, W.dtype), warm, active, st.solver, st.iterations)))
    report("solve_contacts", solve, *per_robot(problem)(model, state, kpa))


if __name__ == "__main__":
    main()
