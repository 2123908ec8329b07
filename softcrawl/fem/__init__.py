"""Full-order finite element engine: static :class:`Model` data, time-varying :class:`State`,
:class:`Control` inputs, and :class:`ImplicitEulerSolver` whose ``step(state, control)`` is the one
entry point (a reduced model plugs in behind the same interface)."""

from softcrawl.fem.body import Body, Cavity, Membrane
from softcrawl.fem.materials import DRAGONSKIN_30, PAPER, PRINTED_POLYMER, LinearElastic
from softcrawl.fem.model import Attachment, Floor, Model, PointRef, embed_point
from softcrawl.fem.solver import ImplicitEulerSolver, SimulationDiverged, SolverSettings, StepStats
from softcrawl.fem.state import Control, State
from softcrawl.fem.static import StaticSolveError, solve_static

__all__ = [
    "Attachment", "Body", "Cavity", "Control", "DRAGONSKIN_30", "Floor", "ImplicitEulerSolver", "LinearElastic",
    "Membrane", "Model", "PAPER", "PRINTED_POLYMER", "PointRef", "SimulationDiverged", "SolverSettings", "State",
    "StaticSolveError", "StepStats", "embed_point", "solve_static",
]
