"""Evaluation: trajectory accuracy through evo (ATE, RPE, merged ATE), plots and reports."""

from como3r.evaluation.report import EvalSummary, evaluate_run
from como3r.evaluation.trajectory import (
    AgentErrors,
    AssociatedPair,
    ErrorStats,
    MergedErrors,
    Sim3Alignment,
    agent_errors,
    associate,
    merged_errors,
    merged_errors_by_component,
)

__all__ = [
    "AgentErrors",
    "AssociatedPair",
    "ErrorStats",
    "EvalSummary",
    "MergedErrors",
    "Sim3Alignment",
    "agent_errors",
    "associate",
    "evaluate_run",
    "merged_errors",
    "merged_errors_by_component",
]
