"""Design-reconfigurable model order reduction: snapshot POD + ECSW hyper-reduction of the
PneuNet leg, placed in any slot of any design, and of the disk (reduction.md; paper sec. IV).

Core (no robot imports): :mod:`~softcrawl.reduction.pod`, :mod:`~softcrawl.reduction.ecsw`,
:mod:`~softcrawl.reduction.model` (part reductions and reduced bodies),
:mod:`~softcrawl.reduction.solver`, :mod:`~softcrawl.reduction.artifact`. The build pipeline
(:mod:`~softcrawl.reduction.scenes`, :mod:`~softcrawl.reduction.runs`,
:mod:`~softcrawl.reduction.build`, :mod:`~softcrawl.reduction.validate`) drives robots.
"""
