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
    claims: dict[str, str] = field(default_factory=dict)
    """The paper's claim behind a comparison, keyed ``"X > Y"`` (a comparison without one is
    ours); the report gives each a verdict from P(X > Y) (``reports/claims.py``)."""
    speed_ratio: tuple[str, str, float] | None = None
    """(X, Y, goal) for runs that adapt pre-trained weights: the report adds each condition's
    coverage before adaptation and area under the curve, and X's mean censored env steps to
    ``metrics.SPEED_AT`` over Y's, against the goal that it be at most ``goal``."""


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


TEAM_MIXED, TEAM_HOMOGENEOUS = "2,2", ("0,4", "4,0")  # the team study's (wheeled,quads)
PAPER_TABLE_II = {"1": "succeed", "2": "failed", "3": "failed", "4": "failed",
                  "5": "failed", "6": "succeed", "7": "failed"}
COMM_CONDITIONS = (*(str(i) for i in range(1, 8)), "1-noinfo")
COMM_CLAIMS = {
    **{f"1 > {c}": f"scheme 1 converges (8 M steps), scheme {c} fails (Table II)"
       for c in ("2", "3", "4", "5", "7")},
    "1 > 6": "scheme 1 converges in 8 M steps, scheme 6 in 14 M: the first scheme yields "
             "better performance (Sec. IV-B)"}

STUDIES: dict[str, Study] = {s.name: s for s in (
    Study("comm", "Table II's 7 communication schemes + scheme 1 without object information",
          _comm_run, conditions=COMM_CONDITIONS,
          # the paper's pick (scheme 1 with object information) against every other scheme
          report=ReportSpec(comparisons=tuple(("1", c) for c in COMM_CONDITIONS[1:]),
                            paper_column="paper (Table II)", paper=PAPER_TABLE_II,
                            claims=COMM_CLAIMS)),
    Study("algo", "POCA vs PPO with the same hyperparameters",
          lambda p: TrialRun(algo=str(p["condition"])), conditions=("poca", "ppo"),
          report=ReportSpec(comparisons=(("poca", "ppo"),), claims={
              "poca > ppo": "POCA's curves converge better than PPO's with the same "
                            "hyperparameters (Sec. IV-B)"})),
    Study("team", "heterogeneous 2 wheeled + 2 quads vs 4 quads vs 4 wheeled",
          _team_run, conditions=(TEAM_MIXED, *TEAM_HOMOGENEOUS),
          report=ReportSpec(comparisons=(("2,2", "0,4"), ("2,2", "4,0")), claims={
              "2,2 > 0,4": "2 wheeled + 2 quads scan more than 4 quads in the same steps "
                           "(Sec. IV-B)"})),
    Study("reward", "individual vs team reward (every robot gets the team sum) x POCA vs PPO",
          lambda p: TrialRun(algo=str(p["condition"]).split("/")[0],
                             env={"reward_mode": str(p["condition"]).split("/")[1]}),
          conditions=("poca/individual", "poca/team", "ppo/individual", "ppo/team"),
          report=ReportSpec(comparisons=(("poca/team", "poca/individual"),
                                         ("ppo/team", "ppo/individual"),
                                         ("poca/team", "ppo/team")), claims={
              # the paper's robots share one team reward that POCA assigns by contribution
              # (Sec. III-B), so its POCA-vs-PPO claim was made with team rewards
              "poca/team > ppo/team": "POCA's curves converge better than PPO's with the "
                                      "same hyperparameters (Sec. IV-B), the team sharing "
                                      "one reward (Sec. III-B)"})),
    Study("hpo", "Optuna TPE over POCA's lr, entropy coefficient, lambda and epochs",
          _hpo_run, space=_hpo_space,
          example={"lr": 3e-4, "entropy_coeff": 5e-3, "lambda_": 0.95, "num_epochs": 3}),
)}

# The meta-MRSS experiment's adaptation runs (conditions are its methods).
PAPER_META_SUCCESS = {"meta-mrss": 87.12, "dr": 68.54, "poca": 60.16, "transfer": 71.74}
META_MRSS_REPORT = ReportSpec(
    comparisons=(("meta-mrss", "dr"), ("meta-mrss", "transfer"), ("meta-mrss", "poca")),
    paper_column="paper success",
    paper={m: f"{v} %" for m, v in PAPER_META_SUCCESS.items()},
    speed_ratio=("meta-mrss", "poca", 0.30),  # issue 16's goal: 80 % in <= 30 % of the steps
    claims={f"meta-mrss > {m}": f"meta-MRSS scans held-out scenes better than {name} "
                                f"(success {PAPER_META_SUCCESS['meta-mrss']} vs "
                                f"{PAPER_META_SUCCESS[m]} %, Sec. IV-A)"
            for m, name in (("dr", "domain randomisation"), ("transfer", "transfer learning"),
                            ("poca", "standard POCA"))})


def get_study(name: str) -> Study:
    from rl_scan.config import fail

    if name not in STUDIES:
        fail("study", name, f"one of {', '.join(STUDIES)}")
    return STUDIES[name]
