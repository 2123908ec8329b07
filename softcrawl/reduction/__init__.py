"""Design-reconfigurable model order reduction: snapshot POD + ECSW hyper-reduction of the
PneuNet leg, placed in any slot of any design, and of the disk (reduction.md; paper sec. IV).

Two layers in one package, on either side of :mod:`softcrawl.robot`:

* The core, below the robot (imports :mod:`softcrawl.fem` and :mod:`softcrawl.geometry`, no
  robot code): :mod:`~softcrawl.reduction.pod`, :mod:`~softcrawl.reduction.ecsw`,
  :mod:`~softcrawl.reduction.model` (part reductions and reduced bodies),
  :mod:`~softcrawl.reduction.floating`, :mod:`~softcrawl.reduction.group`,
  :mod:`~softcrawl.reduction.kernels`, :mod:`~softcrawl.reduction.batch`,
  :mod:`~softcrawl.reduction.solver`, :mod:`~softcrawl.reduction.artifact`. The robot's
  assembly builds its reduced model from these and from nothing else of this package.
* The build pipeline, above the robot: :mod:`~softcrawl.reduction.animations`,
  :mod:`~softcrawl.reduction.scenes` (snapshot and validation scenes),
  :mod:`~softcrawl.reduction.runs`, :mod:`~softcrawl.reduction.build`,
  :mod:`~softcrawl.reduction.validate`. Its arrow up to :mod:`softcrawl.robot` is right: a
  snapshot scene *is* a robot (``assemble_robot`` with one pressure channel per leg), settled
  and stepped by the same episode code (``robot.episode``) that later runs the reduced model,
  so the snapshots see exactly the assembly, contact and settling the reduction must
  reproduce; a copy of that code below the robot would be a second simulator to keep in step,
  and a separate package would only rename the arrow. The robot never imports the pipeline, so
  the arrow closes no cycle (``tests/test_import_graph.py`` checks both directions, counting
  imports inside functions).
"""
