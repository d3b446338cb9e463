"""Runs a study did not train, taken from a study that trained the same trial.

A 1 M-step trial costs ~25 min of a core, so a study need not train again a condition
another study in the same report already trained: the reward study's ``poca/individual``
is the algo study's ``poca`` (individual rewards are the default), a team study's 4
wheeled robots at a point that changes only the quads' settings are another team study's.
Two trials are the same when they resolve to the same algorithm, algorithm settings and
EnvConfig (``trial_key``), trained with the same preset settings (``same_learning``) and
were evaluated on the same schedule with as many episodes.
Borrowed runs join the group under its own condition name with ``borrowed_from`` set;
they are derived on every build and never written to the report's runs file.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import replace
from typing import Any

from rl_scan.reports.collect import Collection, RunRecord
from rl_scan.studies import STUDIES

UNREAD_WITHOUT = {"wheeled": ("wheeled",), "quad": ("quad", "quad_flight_time")}
"""EnvConfig fields no robot reads when a team has none of that kind: 4 wheeled robots
play the same episodes whatever the quads' settings, and 4 quads whatever the wheeled
robots' (``tests/test_hetero_map.py`` checks it step by step)."""


def trial_key(kind: str, condition: str, env: dict[str, Any]) -> str | None:
    """What a study's trial of ``condition`` trains, with the study's EnvConfig overrides
    ``env``: its algorithm, algorithm settings and EnvConfig without the fields its team
    never reads. None: not a condition of a grid study."""
    from rl_scan.config import deep_merge, to_dict
    from rl_scan.envs.sim.env_config import make_env_config

    study = STUDIES.get(kind.removeprefix("study:")) if kind.startswith("study:") else None
    if study is None or condition not in study.conditions:
        return None
    trial = study.run_of({"condition": condition, "seed": 0})
    settings = to_dict(make_env_config(deep_merge(env, trial.env)))
    for robot, count in settings["team"].items():
        if count == 0:
            for unread in UNREAD_WITHOUT[robot]:
                settings.pop(unread)
    return json.dumps({"algo": trial.algo, "algo_kwargs": trial.algo_kwargs,
                       "env": settings}, sort_keys=True)


def _schedule(runs: list[RunRecord]) -> tuple[int, list[float]] | None:
    """The evaluation episodes and env steps of the longest run's evaluations."""
    done = [r for r in runs if r.evals]
    if not done:
        return None
    longest = max(done, key=lambda r: len(r.evals))
    return longest.eval_episodes, [float(e["env_steps"]) for e in longest.evals]


def same_schedule(a: list[RunRecord], b: list[RunRecord]) -> bool:
    """Evaluated as often, with as many episodes, at the same env steps (within 1 %: a
    run's last evaluation is where its last batch ended)."""
    (episodes_a, steps_a), (episodes_b, steps_b) = _schedule(a), _schedule(b)
    return episodes_a == episodes_b and len(steps_a) == len(steps_b) and all(
        abs(x - y) <= 0.01 * max(x, y) for x, y in zip(steps_a, steps_b))


def same_learning(a: list[RunRecord], b: list[RunRecord]) -> bool:
    """Trained with the same preset settings (``RunRecord.learning``), where both sides
    recorded them (runs.json files from before the field hold none: unknown, not refused)."""
    sides = [{json.dumps(r.learning, sort_keys=True) for r in runs if r.learning}
             for runs in (a, b)]
    return not (sides[0] and sides[1]) or sides[0] == sides[1]


def borrow_runs(data: Collection) -> list[RunRecord]:
    """Add to ``data`` (and return) the runs each study group lacks: for every condition
    of its study it has no run of, the runs of the same trial (``trial_key``) from the
    group with the most of them whose preset settings and evaluations match the group's
    own."""
    by_group: dict[str, list[RunRecord]] = defaultdict(list)
    for r in data.runs:
        if not r.borrowed_from:
            by_group[r.group].append(r)
    offers: dict[str, dict[str, list[RunRecord]]] = defaultdict(dict)  # key -> group -> runs
    for group, runs in by_group.items():
        conditions = {r.condition for r in runs}
        for condition in conditions:
            key = trial_key(data.kinds.get(group, ""), condition, data.envs.get(group, {}))
            mine = [r for r in runs if r.condition == condition]
            if key is not None and _schedule(mine) is not None:
                offers[key][group] = mine
    added = []
    for group, runs in sorted(by_group.items()):
        kind = data.kinds.get(group, "")
        study = STUDIES.get(kind.removeprefix("study:")) if kind.startswith("study:") else None
        if study is None or _schedule(runs) is None:
            continue
        own = {r.condition for r in runs}
        for condition in (c for c in study.conditions if c not in own):
            key = trial_key(kind, condition, data.envs.get(group, {}))
            sources = {g: rs for g, rs in offers.get(key, {}).items()
                       if g != group and same_schedule(rs, runs) and same_learning(rs, runs)}
            if not sources:
                continue
            source = max(sorted(sources), key=lambda g: len(sources[g]))
            added += [replace(r, group=group, condition=condition,
                              borrowed_from=(source, r.condition)) for r in sources[source]]
    data.runs += added
    return added


def borrowed_lines(runs: list[RunRecord]) -> list[str]:
    """A group's note on the conditions it borrowed."""
    sources = sorted({(r.condition, *r.borrowed_from) for r in runs if r.borrowed_from})
    if not sources:
        return []
    return ["", "Borrowed runs (the same trial, trained by another study of this report: "
            "the same algorithm, settings, preset and EnvConfig but for the fields its team "
            "never reads, evaluated at the same env steps with as many episodes): " + "; ".join(
                f"**{c}** = {g}'s {theirs}" for c, g, theirs in sources) + "."]
