"""Ground truth of the design space: every design with its best open-loop gait.

The paper reports the design its co-design converged to; this package measures how good that
choice is against the whole space. Each design gets the best gait CMA-ES (the ``cma`` package)
finds in the periodic open-loop gait family (:class:`softcrawl.gaits.periodic.PeriodicGait`) on
the reduced model; designs are then ranked by that reward: the return of the run's task
(:attr:`GroundTruthConfig.task`, :mod:`softcrawl.tasks`; cm of +x crawl per episode for the
paper's ``forward``, degrees for ``turning``), on the design space :attr:`GroundTruthConfig.space`.

**Search** (:mod:`~softcrawl.codesign.groundtruth.search`, a coroutine asking for episodes in
rounds, :func:`design_rounds`, driven by :func:`optimize_design` or, for many designs in
lockstep with each round of every design in flight in one call, :func:`search_many`): for each
cycle length ``L`` in
:attr:`GroundTruthConfig.cycles` a CMA-ES run over the knots of the regulators the design uses
(``m L`` numbers in [0, 90] kPa, step waveform), ``evals_per_cycle`` episodes each, started from
the best of a few structured gaits evaluated first (one regulator after another then vent, all
together, the expert's sampled sine at lags 90/180/270 deg; with :attr:`GroundTruthConfig.seeds`
``"duty"``, the default, the bang-bang duty cycles, :func:`duty_knots`, are screened beside the
runs and the best of them is a finalist too). Episodes are of
``screen_duration`` s when set (screening: :func:`screening_agreement` measures the Spearman
rank correlation of short vs full episodes on a sample: 36 (design, gait) pairs on 6
three-legged designs gave 0.87 / 0.95 / 0.96 for 4 / 6 / 10 s over all pairs, 1.0 for the best
pair per design, 0.43 / 0.75 / 0.79 within a design, hence 6 s and full-length finals); the
``finalists`` best distinct candidates, and the smooth variant of each, are then re-run with full
``duration`` (20 s) episodes, and the best full-episode reward is the design's ground truth. A
diverged episode scores :data:`DIVERGED_CM`.

**Runs** (:func:`run_groundtruth`, ``softcrawl groundtruth``): a folder with ``config.json``
(the :class:`GroundTruthConfig` and the design set, :func:`design_set_spec`: ``--resume``
continues exactly that set), ``results.jsonl`` (one line per finished design, appended and
fsynced as each finishes: a killed run continues where it stopped and never recomputes a
finished design; :mod:`~softcrawl.codesign.groundtruth.store`), ``references.json`` (expert
baseline phase sweep, paper gait on the paper's design), and at the end ``groundtruth.csv``
(ranked table), ``ranked.png`` and ``summary.json``
(:mod:`~softcrawl.codesign.groundtruth.outputs`); the files other than ``results.jsonl`` are
replaced atomically (:func:`softcrawl.safeio.atomic_write_text`). The folder must be new, empty
or a ground truth (:func:`check_folder`), and is locked while a run writes it
(:func:`folder_lock`).

Modules, each importing only those before it: ``config`` → ``result`` → ``search`` →
``optimize`` → ``store`` → ``outputs`` → ``runner``.
"""

from softcrawl.codesign.groundtruth.config import (
    MAX_EVALS,
    MAX_FINALISTS,
    MAX_POPSIZE,
    GroundTruthConfig,
    design_set_spec,
    gt_robot,
    parse_designs,
)
from softcrawl.codesign.groundtruth.optimize import (
    DesignEvaluator,
    SerialEvaluateMany,
    episode_return,
    optimize_design,
    screening_agreement,
    spearman,
)
from softcrawl.codesign.groundtruth.outputs import competition_ranks, write_outputs
from softcrawl.codesign.groundtruth.result import DIVERGED_CM, DesignResult
from softcrawl.codesign.groundtruth.runner import (
    EXECUTORS,
    PAPER_L1_CM,
    references,
    run_groundtruth,
)
from softcrawl.codesign.groundtruth.search import (
    EvaluateMany,
    cma_generations,
    cma_maximize,
    cma_search,
    design_rounds,
    design_search,
    design_seed,
    drive,
    duty_knots,
    knots_to_gait,
    one_at_a_time,
    search_many,
    seed_knots,
    used_regulators,
)
from softcrawl.codesign.groundtruth.store import (
    LOCK,
    RESULTS,
    check_folder,
    folder_lock,
    folder_task,
    load_groundtruth,
    load_results,
    read_config,
    read_references,
    read_results,
    recorded_designs,
)
from softcrawl.gaits.periodic import MAX_KNOTS, WAVEFORMS, PeriodicGait
from softcrawl.safeio import FolderLockedError

__all__ = [
    "DIVERGED_CM",
    "EXECUTORS",
    "LOCK",
    "MAX_EVALS",
    "MAX_FINALISTS",
    "MAX_KNOTS",
    "MAX_POPSIZE",
    "PAPER_L1_CM",
    "RESULTS",
    "WAVEFORMS",
    "DesignEvaluator",
    "DesignResult",
    "EvaluateMany",
    "FolderLockedError",
    "GroundTruthConfig",
    "PeriodicGait",
    "SerialEvaluateMany",
    "check_folder",
    "cma_generations",
    "cma_maximize",
    "cma_search",
    "competition_ranks",
    "design_rounds",
    "design_search",
    "design_set_spec",
    "design_seed",
    "drive",
    "duty_knots",
    "episode_return",
    "folder_lock",
    "folder_task",
    "gt_robot",
    "knots_to_gait",
    "load_groundtruth",
    "load_results",
    "optimize_design",
    "parse_designs",
    "read_config",
    "read_references",
    "read_results",
    "recorded_designs",
    "one_at_a_time",
    "references",
    "run_groundtruth",
    "screening_agreement",
    "search_many",
    "seed_knots",
    "spearman",
    "used_regulators",
    "write_outputs",
]
