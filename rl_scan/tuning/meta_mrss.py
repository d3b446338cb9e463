"""``rl-scan experiment meta-mrss``: the paper's protocol (Sec. IV-B) on held-out scenarios.

Methods (each gets the same pre-training budget, then the same adaptation budget):
  meta-mrss  MetaPOCA meta-trained on train scenarios, then adapted (POCA) per test scene;
  dr         domain randomisation: POCA on a fresh train scenario every episode (train:*),
             then fine-tuned per test scene;
  transfer   transfer learning: POCA trained on one train scenario (train:0), then
             fine-tuned per test scene;
  poca       standard POCA, from scratch on each test scene (no pre-training).
Adaptation is POCA training started from the method's weights on ``test:N``, evaluated
every ``eval_interval`` iterations. From each adaptation curve (evaluation coverage over
adaptation env steps) we take, defined up front:
  final coverage  the last evaluation's mean coverage (the paper's "scanning success rate");
  steps to 80 %   the env steps of the first of two consecutive evaluations with mean
                  coverage >= 0.8 (one noisy evaluation does not count); a run that never
                  gets there counts as the whole adaptation budget (censored), and the share
                  of runs that got there is reported beside it;
  area            the area under the coverage curve over the budget, as a fraction;
  success         the last evaluation's fraction of episodes with coverage >= 95 %.
Evaluations use ``eval_episodes`` episodes (10 in the quick and paper protocols). Every
method is summarised on the same (scene, seed) pairs: those all methods have finished.

Layout: an experiment folder of ``rl_scan.results``: its pre-training and adaptation runs
are ordinary run folders, and a summary (JSON) and a table (Markdown) hold the results. A
finished run has a ``DONE`` file; re-running the command skips finished runs and resumes
interrupted ones. Independent
runs go side by side (``jobs.py``).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rl_scan import metrics as M
from rl_scan import results as R
from rl_scan.algorithms.registry import get_algorithm
from rl_scan.config import ConfigError, check_range, fail
from rl_scan.envs.sim.scenarios import N_TEST
from rl_scan.reports.stats import sample_std
from rl_scan.studies import META_MRSS_REPORT, PAPER_META_SUCCESS
from rl_scan.tuning.driver import make_run_spec, required_cpus
from rl_scan.tuning.jobs import Job, run_jobs
from rl_scan.tuning.launch import check_resources, init_ray, largest_per_node, scenario_label
from rl_scan.tuning.presets import PROTOCOLS, Protocol, get_preset

METHODS = ("meta-mrss", "dr", "transfer", "poca")
# method -> (algorithm, pre-training scenario); "poca" has no pre-training
PRETRAIN = {"meta-mrss": ("meta-poca", "train:*"), "dr": ("poca", "train:*"),
            "transfer": ("poca", "train:0")}


def parse_tests(text: str) -> list[str]:
    """'0,1,4' or 'test:0,test:3' -> ['test:0', ...]; train scenarios are refused."""
    out = []
    for item in [t.strip() for t in str(text).split(",") if t.strip()]:
        name = item if ":" in item else f"test:{item}"
        kind, _, index = name.partition(":")
        if kind == "train":
            raise ConfigError(f"tests: {name!r} is in the train set; held-out scenarios "
                              f"are test:0 .. test:{N_TEST - 1}")
        if kind != "test" or not index.isdigit() or not 0 <= int(index) < N_TEST:
            fail("tests", item, f"test scenario indices 0..{N_TEST - 1} (e.g. 0,1,2)")
        out.append(f"test:{int(index)}")
    if not out:
        fail("tests", text, f"at least one of 0..{N_TEST - 1}")
    return out


def validate(methods: list[str], tests: list[str], seeds: int, protocol: Protocol,
             first_seed: int = 0) -> None:
    for m in methods:
        if m not in METHODS:
            fail("methods", m, f"any of {', '.join(METHODS)}")
    if not methods:
        fail("methods", "", f"any of {', '.join(METHODS)}")
    check_range("seeds", seeds, 1, 100)
    check_range("seed", first_seed, 0, 10_000)
    check_range("pretrain_steps", protocol.pretrain_steps, 1)
    check_range("adapt_steps", protocol.adapt_steps, 1)
    check_range("eval_interval", protocol.eval_interval, 1)
    check_range("eval_episodes", protocol.eval_episodes, 1)


def plan_jobs(root: Path, methods: list[str], tests: list[str], seeds: int,
              protocol: Protocol, env_config: dict[str, Any],
              preset_overrides: dict[str, Any] | None = None,
              meta_settings: dict[str, Any] | None = None, first_seed: int = 0) -> list[Job]:
    """Every run of the protocol, seed by seed (seeds ``first_seed`` ..
    ``first_seed + seeds - 1``, the order runs start in): each method's
    pre-training, then its adaptation to every test scene (which waits for it).
    ``preset_overrides`` (e.g. the sampler) apply to every run, ``meta_settings``
    (MetaPOCA's, over its preset's) to meta-MRSS's pre-training."""
    common = dict(preset_overrides or {})
    jobs = []
    for seed in range(first_seed, first_seed + seeds):
        for method in methods:
            pre = None
            if method in PRETRAIN:
                algo, scenario = PRETRAIN[method]
                overrides = {**common, "total_env_steps": protocol.pretrain_steps}
                settings = meta_settings if method == "meta-mrss" else None
                if get_algorithm(algo).local_sampling:
                    overrides.update(num_env_runners=0)
                pre = Job(f"pre-train {method} (seed {seed}, {protocol.pretrain_steps:,} "
                          "env steps)", root / R.PRETRAIN_DIR, f"{method}_s{seed}",
                          dict(algo=algo, env_config={**env_config, "scenario": scenario},
                               preset_name=protocol.train_preset, seed=seed,
                               preset_overrides=overrides, settings_overrides=settings),
                          env_steps=protocol.pretrain_steps)
                jobs.append(pre)
            for test in tests:
                jobs.append(Job(
                    f"adapt {method} on {test} (seed {seed}, {protocol.adapt_steps:,} env "
                    "steps)", root / R.ADAPT_DIR, f"{method}_{scenario_label(test)}_s{seed}",
                    dict(algo="poca", env_config={**env_config, "scenario": test},
                         preset_name=protocol.train_preset, seed=seed,
                         init_from=pre.folder / pre.name if pre else None,
                         preset_overrides={**common, "total_env_steps": protocol.adapt_steps,
                                           "evaluation_interval": protocol.eval_interval,
                                           "evaluation_episodes": protocol.eval_episodes}),
                    after=pre, env_steps=protocol.adapt_steps))
    return jobs


def check_jobs(jobs: list[Job]) -> None:
    """Build every run's algorithm config (without Ray) so bad settings fail up front."""
    seen = set()
    for job in jobs:
        kw = job.kwargs
        key = (kw["algo"], kw["env_config"]["scenario"])
        if key not in seen:
            seen.add(key)
            make_run_spec(kw["algo"], kw["env_config"], kw["preset_name"], seed=kw["seed"],
                          preset_overrides=kw["preset_overrides"],
                          settings_overrides=kw.get("settings_overrides")).algorithm_config()


def check_same_meta_settings(root: Path, meta_settings: dict[str, Any]) -> None:
    """A re-run resumes the experiment it finds: its meta-MRSS runs were started with the
    meta settings recorded then, which a resume cannot change."""
    file = root / R.PROTOCOL_FILE
    if not file.is_file():
        return
    recorded = (R.read_yaml(file) or {}).get("meta_settings") or {}
    if recorded != meta_settings:
        fail("meta", meta_settings or "(none)",
             f"the settings {root} was started with ({recorded or 'none'}): re-running "
             "resumes it; a new --name starts a new experiment")


@dataclass(frozen=True)
class Overrides:
    """What an experiment changes from its protocol preset (each empty by default)."""

    budgets: dict[str, int] = field(default_factory=dict)
    """Protocol fields, e.g. ``{"pretrain_steps": 1_000_000}``."""
    runs: dict[str, Any] = field(default_factory=dict)
    """Train preset fields of every run, e.g. ``{"sampler": "rllib"}``."""
    meta: dict[str, Any] = field(default_factory=dict)
    """MetaPOCA settings of meta-MRSS's pre-training, e.g. ``{"relabel_query": True}``."""


def run_protocol(results_dir: str | Path, name: str, *, preset: str = "quick",
                 methods: tuple[str, ...] | list[str] = METHODS, tests: list[str] | None = None,
                 seeds: int = 3, first_seed: int = 0,
                 env_config: dict[str, Any] | None = None,
                 overrides: Overrides | None = None, jobs: int | None = None,
                 address: str | None = None, console=None) -> dict:
    """Pre-train and adapt every method on every test scene and seed; returns the summary.

    ``jobs`` runs at once (default: as many as the Ray cluster's CPUs hold). The seeds are
    ``first_seed`` .. ``first_seed + seeds - 1``: a protocol too long for one sitting runs
    a seed at a time (in other sessions or on other machines) and ``rl-scan report --add``
    joins the parts.
    """
    from rich.console import Console

    console = console or Console()
    overrides = overrides or Overrides()
    if preset not in PROTOCOLS:
        fail("preset", preset, f"one of {sorted(PROTOCOLS)}")
    protocol = Protocol(**{**PROTOCOLS[preset].__dict__, **overrides.budgets})
    preset_overrides = overrides.runs or None
    tests = tests or [f"test:{i}" for i in range(N_TEST)]
    methods = list(methods)
    validate(methods, tests, seeds, protocol, first_seed)
    meta_settings = dict(overrides.meta)
    if meta_settings and "meta-mrss" not in methods:
        fail("meta", ",".join(f"{k}={v}" for k, v in meta_settings.items()),
             "none unless the methods include meta-mrss (only its pre-training uses them)")
    if jobs is not None:
        check_range("jobs", jobs, 1)
    env_config = dict(env_config or {})
    root = Path(results_dir).resolve() / name
    plan = plan_jobs(root, methods, tests, seeds, protocol, env_config, preset_overrides,
                     meta_settings, first_seed)
    check_jobs(plan)
    check_same_meta_settings(root, meta_settings)
    run_preset = get_preset(protocol.train_preset, preset_overrides)
    need = required_cpus(run_preset)
    cpus = _available_cpus(address)
    check_resources(run_preset, cpus, largest_per_node())
    most = max(1, int(cpus) // need)
    if jobs is not None and jobs > most:
        fail("jobs", jobs, f"at most {most} on this Ray cluster ({cpus:g} CPUs, {need} per run)")
    workers = min(jobs or most, len(plan))
    root.mkdir(parents=True, exist_ok=True)
    R.write_yaml(root / R.PROTOCOL_FILE, {  # lets a report say what is missing
        "preset": preset, "methods": methods, "tests": tests, "seeds": seeds,
        "first_seed": first_seed,
        "protocol": dict(protocol.__dict__), "meta_settings": meta_settings,
        "planned_runs": {kind: sum(j.folder.name == kind for j in plan)
                         for kind in (R.PRETRAIN_DIR, R.ADAPT_DIR)}})
    console.print(f"[bold]meta-mrss[/]: {len(plan)} runs, {workers} at a time -> {root}")
    run_jobs(plan, workers, console, address=address)
    summary = summarize(root, methods, tests, seeds, budget=protocol.adapt_steps,
                        first_seed=first_seed)
    R.write_json(root / R.SUMMARY_FILE, summary)
    (root / R.TABLE_FILE).write_text(format_table(summary))
    console.print(format_table(summary))
    return summary


def summarize(root: Path, methods: list[str], tests: list[str], seeds: int,
              budget: float, first_seed: int = 0) -> dict:
    """Per method: each seed's mean over the test scenes, then mean and sample std over
    seeds. Every method is summarised on the same (scene, seed) pairs: those that all
    methods have finished; the others are listed as missing or left out."""
    seed_range = range(first_seed, first_seed + seeds)
    curves: dict[tuple[str, str, int], list] = {}
    out: dict[str, Any] = {"methods": {}, "missing": [], "left_out": []}
    for method in methods:
        for seed in seed_range:
            for test in tests:
                run = root / R.ADAPT_DIR / f"{method}_{scenario_label(test)}_s{seed}"
                if (run / R.EVAL_FILE).is_file():
                    curves[method, test, seed] = R.read_evals(run)
                else:
                    out["missing"].append(str(run))
    common = [(t, s) for s in seed_range for t in tests
              if all((m, t, s) in curves for m in methods)]
    out["left_out"] = sorted(f"{m}_{scenario_label(t)}_s{s}" for (m, t, s) in curves
                             if (t, s) not in common)
    out["common"] = [f"{t} s{s}" for t, s in common]
    keys = ("final_coverage", "steps_to_80", "reached_80", "auc", "success", "start_coverage")
    for method in methods:
        per_seed: dict[str, list[float]] = {k: [] for k in keys}
        runs = {}
        for seed in seed_range:
            rows = []
            for test in (t for t, s in common if s == seed):
                entries = curves[method, test, seed]
                rows.append(M.curve_metrics(entries, budget))
                runs[f"{method}_{scenario_label(test)}_s{seed}"] = {
                    "curve": [(e["env_steps"], e[M.COVERAGE]) for e in entries], **rows[-1]}
            if rows:
                for k in keys:
                    per_seed[k].append(_nanstat(np.nanmean, [r[k] for r in rows]))
        out["methods"][method] = {
            k: {"mean": _nanstat(np.nanmean, v), "std": sample_std(v), "values": v}
            for k, v in per_seed.items()}
        out["methods"][method]["runs"] = runs
    gains = [R.adaptation_gain(R.read_json(run / R.META_FILE) or [])
             for seed in seed_range if "meta-mrss" in methods
             if (run := root / R.PRETRAIN_DIR / f"meta-mrss_s{seed}").is_dir()]
    if gains:
        out["meta_training"] = {k: {"mean": _nanstat(np.nanmean, [g[k] for g in gains]),
                                    "std": sample_std([g[k] for g in gains]),
                                    "values": [g[k] for g in gains]}
                                for k in ("gain", "delta_norm")}
    return out


def _available_cpus(address: str | None) -> float:
    """CPUs of the cluster at ``address`` (or of the Ray this process runs), else of this
    machine (local child runs start Ray themselves)."""
    import ray

    if address or ray.is_initialized():
        return init_ray(address)
    return float(os.cpu_count() or 1)


def _nanstat(func, values: list[float]) -> float:
    vals = np.asarray(values, dtype=float)
    return float(func(vals)) if len(vals) and not np.all(np.isnan(vals)) else math.nan


def format_table(summary: dict) -> str:
    """Markdown: method x (zero-shot coverage, final coverage, censored steps to 80 %, area
    under the curve, success), mean +- sample std over seeds, the paper's figures beside."""
    lines = ["| method | coverage % before adaptation (zero-shot) | final coverage % | "
             "env steps to 80 % (censored; runs reaching it) | area under the coverage "
             "curve % | success % | paper's scanning success % |",
             "|---|---|---|---|---|---|---|"]

    def pm(stats, key, scale=1.0, fmt="{:.1f}"):
        m, sd = stats[key]["mean"], stats[key]["std"]
        return "-" if math.isnan(m) else f"{fmt.format(m * scale)} ± {fmt.format(sd * scale)}"

    for method, s in summary["methods"].items():
        reach = s["reached_80"]["mean"]
        lines.append(f"| {method} | {pm(s, 'start_coverage', 100)} | "
                     f"{pm(s, 'final_coverage', 100)} | "
                     f"{pm(s, 'steps_to_80', 1, '{:,.0f}')} "
                     f"({'-' if math.isnan(reach) else f'{100 * reach:.0f} %'}) | "
                     f"{pm(s, 'auc', 100)} | "
                     f"{pm(s, 'success', 100)} | {PAPER_META_SUCCESS.get(method, '-')} |")
    x, y, goal = META_MRSS_REPORT.speed_ratio
    meta, poca = summary["methods"].get(x), summary["methods"].get(y)
    if meta and poca:
        a, b = meta["steps_to_80"]["mean"], poca["steps_to_80"]["mean"]
        ratio = "-" if math.isnan(a) or math.isnan(b) else f"{a / b:.2f}"
        lines.append(f"\nmeta-MRSS / standard POCA env steps to 80 % (censored): {ratio} "
                     f"(goal <= {goal:.2f})")
    meta_training = summary.get("meta_training")
    if meta_training:
        gain, norm = meta_training["gain"], meta_training["delta_norm"]
        lines.append(f"\nmeta-training, last half of its meta-iterations (mean ± std over "
                     f"seeds): adaptation gain (query coverage with the adapted weights - "
                     f"support coverage with the meta weights) {100 * gain['mean']:+.1f} ± "
                     f"{100 * gain['std']:.1f} points; inner-update step ||delta|| "
                     f"{norm['mean']:.3g}")
    lines.append(f"\nscenes x seeds every method finished (all compared on these): "
                 f"{len(summary.get('common', []))}")
    if summary["missing"]:
        lines.append(f"\nmissing runs ({len(summary['missing'])}): "
                     + ", ".join(Path(m).name for m in summary["missing"]))
    if summary.get("left_out"):
        lines.append(f"\nleft out (another method lacks that scene and seed) "
                     f"({len(summary['left_out'])}): " + ", ".join(summary["left_out"]))
    return "\n".join(lines) + "\n"
