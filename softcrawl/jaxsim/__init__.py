"""softcrawl's reduced robot in JAX: one jitted step for a batch of robots on a CPU or a GPU.

The same physics as the CPU reduced engine (:class:`softcrawl.reduction.solver.ReducedSolver`
with a floating-frame disk, the default reduced robot): POD + ECSW legs placed from the shipped
leg reduction, the disk linear elastic in one floating frame, point attachments, a flat floor
with Coulomb friction, regulators with the real-to-sim pressure warp. What differs is how the
work is laid out: fixed shapes so that ``jax.vmap`` runs many robots (of mixed designs) at
once and ``jax.lax.scan`` runs many steps in one compiled call; the Delassus operator is
assembled by blocks and the attachments eliminated (:mod:`~softcrawl.jaxsim.delassus`,
:mod:`~softcrawl.jaxsim.elimination`), and the contact problem over the ``K``
lowest contact points is solved with a fixed number of unrolled accelerated projected gradient
iterations, warm-started from the last step (:mod:`~softcrawl.jaxsim.contact`), instead of the CPU
engine's growing contact set, Gauss-Seidel and exact active-set polish: a step is a short chain
of dependent operations, what sets its latency on a GPU (:mod:`~softcrawl.jaxsim.cost`,
``benchmarks/step_cost.py``).

Data layout (Model / State / Control, as NVIDIA Warp and Newton split them):

* :class:`~softcrawl.jaxsim.model.Model` (:mod:`softcrawl.jaxsim.model`): static arrays. The leg
  part (RID elements with the basis rows of their nodes only, cavity, collision and attachment
  nodes; part frame) and the disk (rest positions, masses, dense ``K_0`` and ``A_0^-1``) are
  shared by all robots; per robot (leading batch axis) each of ``L`` leg slots' rotation,
  translation, regulator channel and mask, and the disk side of its attachments. Scalar
  settings (dt, damping, floor, ``K``, the contact solver and its iterations) are static.
* :class:`~softcrawl.jaxsim.engine.State`: per robot, the legs' modal displacements and velocities
  ``q, qdot`` ``(L, m)`` (part frame), the disk's node positions and velocities ``(n, 3)``, the
  contact points and impulses of the last step (warm start), the regulators' pressures, time.
* :class:`~softcrawl.jaxsim.engine.Control`: the regulator commands, real kPa ``(R,)`` (one per regulator of the
  design space).

:func:`~softcrawl.jaxsim.engine.step` advances one robot one ``dt``;
:func:`~softcrawl.jaxsim.engine.make_rollout` gives the jitted, vmapped rollout of a batch for one
action, :func:`~softcrawl.jaxsim.engine.make_schedule_rollout` for per-step commands, and
:func:`~softcrawl.jaxsim.engine.make_settle` settles a batch to rest.
:class:`~softcrawl.jaxsim.episodes.JaxEvaluator` runs open-loop episodes of many designs and gaits
in batches (what the ground truth's design evaluator does on the CPU), and
:func:`~softcrawl.jaxsim.scenes.run_scene` the reduction's validation scenes
(``softcrawl reduce validate --engine jax``).
:func:`~softcrawl.jaxsim.model.build_model` makes the model of a list of reduced robots
(``RobotConfig(model="reduced")``, the default floating disk), padding every robot to the most
legs among them (absent legs masked: one compiled program per leg-slot count, and a batch of
mixed designs pays for its largest; grouping designs by leg count is the caller's choice);
:func:`~softcrawl.jaxsim.model.select_robots` repeats its robots into a batch. float32 or float64
follow ``jax_enable_x64``, which the caller sets (never at import).
:mod:`~softcrawl.jaxsim.contact` holds the constraint solve (attachments and frictional floor
contact) of one robot with fixed, padded shapes, ``jax.vmap``-ped over the batch by the engine;
:mod:`~softcrawl.jaxsim.fused` runs its accelerated-gradient solve in one GPU kernel per robot,
both forms on :mod:`~softcrawl.jaxsim.cone`'s arithmetic; :mod:`~softcrawl.jaxsim.factor`
inverts the step's Cholesky factors, by the library or in one GPU kernel per matrix.
For a vector env (:mod:`softcrawl.envs.backends.jaxvec`): :mod:`~softcrawl.jaxsim.rig` gives each
robot its own regulators and pressure warp and stops a robot where it diverged
(:func:`~softcrawl.jaxsim.rig.make_action_rollout`); :mod:`~softcrawl.jaxsim.batch` writes rows into
a batch by index and settles new robots together. :mod:`~softcrawl.jaxsim.tables` gathers any
design's rows from per-slot tables of its design space (no robot built per design) and caches
rested states on disk.
"""
