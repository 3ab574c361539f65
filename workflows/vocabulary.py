"""The words a workflow is asked and answered in, for the surfaces that ask: the estimation methods and the
presets (`models.presets`), a gap plan (`estimators.gap_plan`), an evaluation's settings
(`estimators.evaluation_settings`), the errors a refusal raises (`learnest.errors`),
a gain in percent and whether a flight got worse beyond its interval (`estimators.metrics`), and this release.

The CLI checks its arguments with these before anything heavy loads: importing this module loads numpy and
plain Python only (no torch, SciPy, CasADi, pandas, SQL or web code).
"""
from __future__ import annotations

from learnest import __version__
from learnest.errors import InvalidInput, LearnestError
from learnest.estimators.evaluation_settings import EvaluationSettings
from learnest.estimators.gap_plan import GapPlan
from learnest.estimators.metrics import gain_pct, worse_beyond_interval
from learnest.models.presets import (
    CRAZYFLIE_TRAINING,
    DIAGNOSIS_SPLIT_RULE,
    EVALUATION_METHODS,
    GAP_EVERY_S,
    GAP_S,
    GAP_START_S,
    METHODS,
    MHE_HORIZON,
    MIN_GAP_S,
    PAPER_OBSERVER,
    PRODUCTION_ALIAS,
    SG_WINDOW,
    SG_WINDOW_RANGE,
    gap_plan_problem,
    parse_methods,
)

__all__ = ["CRAZYFLIE_TRAINING", "DIAGNOSIS_SPLIT_RULE", "EVALUATION_METHODS", "GAP_EVERY_S", "GAP_S", "GAP_START_S",
           "METHODS", "MHE_HORIZON", "MIN_GAP_S", "PAPER_OBSERVER", "PRODUCTION_ALIAS", "SG_WINDOW", "SG_WINDOW_RANGE",
           "EvaluationSettings", "GapPlan", "InvalidInput", "LearnestError", "__version__", "gain_pct",
           "gap_plan_problem", "parse_methods", "worse_beyond_interval"]
