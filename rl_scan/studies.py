"""The study registry: every ablation study, and what the report compares, in one place.

A study is a set of conditions (a full grid of condition x seed, searched by Optuna's
``GridSampler``) or a search space (Optuna's TPE), plus how one trial's parameters become
a training run and which comparisons the report makes. The command line, the ablation
runner (``tuning/ablate.py``) and the report read this module; adding a study is one
entry in ``STUDIES`` (and its test).

It imports neither Ray nor Optuna at module level, so ``--help`` and reports stay fast.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class TrialRun:
    """What one trial trains: an algorithm, EnvConfig overrides, algorithm settings."""

    algo: str = "poca"
    env: dict[str, Any] = field(default_factory=dict)
    algo_kwargs: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ReportSpec:
    """What a report shows for a group of runs beside its per-condition table."""

    comparisons: tuple[tuple[str, str], ...] = ()
    """(X, Y) condition pairs whose probability of improvement P(X > Y) is reported."""
    paper_column: str | None = None
    """Title of the table column with the paper's figure per condition."""
    paper: dict[str, str] = field(default_factory=dict)
    """The paper's figure per condition (conditions it does not have show a dash)."""


@dataclass(frozen=True)
class Study:
    """One ablation study of ``rl-scan ablate``."""

    name: str
    summary: str
    """One line for ``--help``."""
    run_of: Callable[[dict[str, Any]], TrialRun]
    """A trial's parameters (``condition`` or searched values, and ``seed``) -> its run."""
    conditions: tuple[str, ...] = ()
    """Grid studies: the conditions, each run with every seed."""
    space: Callable[[], dict[str, Any]] | None = None
    """Search studies: Optuna distributions of the searched parameters (TPE sampler)."""
    example: dict[str, Any] = field(default_factory=dict)
    """Search studies: parameters checked before Ray starts."""
    report: ReportSpec = field(default_factory=ReportSpec)

    @property
    def is_grid(self) -> bool:
        return bool(self.conditions)

    def example_params(self) -> list[dict[str, Any]]:
        """One parameter set per condition (or the example): every one builds up front."""
        if self.is_grid:
            return [{"condition": c, "seed": 0} for c in self.conditions]
        return [{**self.example, "seed": 0}]


def _comm_run(params: dict[str, Any]) -> TrialRun:
    scheme, _, info = str(params["condition"]).partition("-")
    return TrialRun(env={"comm_scheme": int(scheme), "object_info": info != "noinfo"})


def _team_run(params: dict[str, Any]) -> TrialRun:
    wheeled, quad = (int(x) for x in str(params["condition"]).split(","))
    return TrialRun(env={"team": {"wheeled": wheeled, "quad": quad}})


def _hpo_run(params: dict[str, Any]) -> TrialRun:
    kwargs = {k: params[k] for k in ("lr", "entropy_coeff", "lambda_")}
    return TrialRun(algo_kwargs={**kwargs, "num_epochs": int(params["num_epochs"])})


def _hpo_space() -> dict[str, Any]:
    from optuna.distributions import FloatDistribution, IntDistribution

    return {"lr": FloatDistribution(5e-5, 2e-3, log=True),
            "entropy_coeff": FloatDistribution(1e-4, 2e-2, log=True),
            "lambda_": FloatDistribution(0.8, 0.99),
            "num_epochs": IntDistribution(1, 5)}


PAPER_TABLE_II = {"1": "succeed", "2": "failed", "3": "failed", "4": "failed",
                  "5": "failed", "6": "succeed", "7": "failed"}
COMM_CONDITIONS = (*(str(i) for i in range(1, 8)), "1-noinfo")

STUDIES: dict[str, Study] = {s.name: s for s in (
    Study("comm", "Table II's 7 communication schemes + scheme 1 without object information",
          _comm_run, conditions=COMM_CONDITIONS,
          # the paper's pick (scheme 1 with object information) against every other scheme
          report=ReportSpec(comparisons=tuple(("1", c) for c in COMM_CONDITIONS[1:]),
                            paper_column="paper (Table II)", paper=PAPER_TABLE_II)),
    Study("algo", "POCA vs PPO with the same hyperparameters",
          lambda p: TrialRun(algo=str(p["condition"])), conditions=("poca", "ppo"),
          report=ReportSpec(comparisons=(("poca", "ppo"),))),
    Study("team", "heterogeneous 2 wheeled + 2 quads vs 4 quads vs 4 wheeled",
          _team_run, conditions=("2,2", "0,4", "4,0"),
          report=ReportSpec(comparisons=(("2,2", "0,4"), ("2,2", "4,0")))),
    Study("reward", "individual vs team reward (every robot gets the team sum) x POCA vs PPO",
          lambda p: TrialRun(algo=str(p["condition"]).split("/")[0],
                             env={"reward_mode": str(p["condition"]).split("/")[1]}),
          conditions=("poca/individual", "poca/team", "ppo/individual", "ppo/team"),
          report=ReportSpec(comparisons=(("poca/team", "poca/individual"),
                                         ("ppo/team", "ppo/individual"),
                                         ("poca/team", "ppo/team")))),
    Study("hpo", "Optuna TPE over POCA's lr, entropy coefficient, lambda and epochs",
          _hpo_run, space=_hpo_space,
          example={"lr": 3e-4, "entropy_coeff": 5e-3, "lambda_": 0.95, "num_epochs": 3}),
)}

# The meta-MRSS experiment's adaptation runs (conditions are its methods).
PAPER_META_SUCCESS = {"meta-mrss": 87.12, "dr": 68.54, "poca": 60.16, "transfer": 71.74}
META_MRSS_REPORT = ReportSpec(
    comparisons=(("meta-mrss", "dr"), ("meta-mrss", "transfer"), ("meta-mrss", "poca")),
    paper_column="paper success",
    paper={m: f"{v} %" for m, v in PAPER_META_SUCCESS.items()})


def get_study(name: str) -> Study:
    from rl_scan.config import fail

    if name not in STUDIES:
        fail("study", name, f"one of {', '.join(STUDIES)}")
    return STUDIES[name]
