from __future__ import annotations

import argparse

from rl_scan.algorithms.registry import ALGORITHMS, DEFAULT_SAMPLER, SAMPLERS
from rl_scan.cli import commands
from rl_scan.results import (
    BEST_EVAL_FILE,
    EVAL_FILE,
    PROGRESS_FILE,
    RUN_FILE,
    TRAIN_TRIAL,
    TUNE_DIR,
)
from rl_scan.studies import STUDIES
from rl_scan.tuning.presets import PRESETS, PROTOCOLS

EXAMPLES = """examples:
  rl-scan scenario show ablation
  rl-scan scenario show test:3 --team 1,3
  rl-scan scenario export train:12 scene.yaml
  rl-scan bench env --seconds 3
  rl-scan render --scenario test:0 --out runs/test0.gif --every 5
  rl-scan train --algo ppo --preset smoke --scenario ablation
"""


def _add_run_args(p: argparse.ArgumentParser, default_name: str) -> None:
    """Options every Tune-launched run shares (train, meta-train, adapt)."""
    p.add_argument("--preset", choices=tuple(PRESETS), default="quick",
                   help="budget: smoke (seconds), quick (minutes, default), paper (cluster)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the run (ablate: the first seed; --seeds count from it)")
    p.add_argument("--results", default="results", help="results folder (default results/)")
    p.add_argument("--name", default=None, help=f"run name (default {default_name})")
    p.add_argument("--address", default=None, help="Ray cluster address (default: local)")
    p.add_argument("--resume", action="store_true", help="continue the run named --name")
    p.add_argument("--num-env-runners", type=int, default=None,
                   help="remote sampling actors (preset default; each needs a CPU)")
    p.add_argument("--envs-per-runner", type=int, default=None, help="envs per env runner")
    p.add_argument("--learner-cpus", type=int, default=None,
                   help="CPUs (torch threads) of each run's training process (preset default "
                        "1; a lone run on an idle 2-core machine learns ~1.5x faster with 2)")
    p.add_argument("--overlap", dest="overlap_sampling", action="store_true", default=None,
                   help="remote env runners sample the next batch while the learner trains "
                        "on this one (needs --num-env-runners >= 1; one iteration of policy "
                        "lag)")
    p.add_argument("--eval-episodes", dest="evaluation_episodes", type=int, default=None,
                   help="episodes per training-time evaluation (preset default; quick: 3)")
    p.add_argument("--eval-interval", dest="evaluation_interval", type=int, default=None,
                   help="training iterations between evaluations (preset default; quick: 5)")
    _add_sampler_arg(p)
    _add_resources_arg(p)


def _add_resources_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trial-resources", dest="custom_resources", type=parse_resources,
                   default=None, metavar="NAME=AMOUNT[,...]",
                   help="custom Ray resources each run asks for, to pin runs to the nodes "
                        "that offer them (e.g. trial_slot=1; docs/cluster.md)")


def parse_resources(text: str) -> dict[str, float]:
    """'a=1,b=0.5' -> {'a': 1.0, 'b': 0.5} (argparse reports a bad item as one line)."""
    out = {}
    for item in filter(None, text.split(",")):
        name, sep, amount = item.partition("=")
        try:
            out[name.strip()] = float(amount)
        except ValueError:
            sep = ""
        if not sep or not name.strip():
            raise argparse.ArgumentTypeError(f"{item!r} is not NAME=AMOUNT")
    return out


def _add_sampler_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sampler", choices=tuple(SAMPLERS), default=None,
                   help="; ".join(f"{k}: {v}" for k, v in SAMPLERS.items())
                   + f" (default {DEFAULT_SAMPLER})")


def _add_meta_arg(parser: argparse.ArgumentParser) -> None:
    """--meta KEY=VALUE: MetaPOCA settings over the preset's (meta-train, the protocol)."""
    parser.add_argument("--meta", action="append", default=[], metavar="KEY=VALUE",
                        help="a meta setting over the preset's: tasks, support_steps, "
                             "query_steps, inner_updates, inner_lr (the inner updates' lr as "
                             "a multiple of POCA's), inner_adam (fresh, meta or scale), outer "
                             "(maml; maml_dr: maml whose update at theta also learns from "
                             "the query batches; reptile; or multitask: the control without "
                             "the MAML shift), reptile_lr, maml_weight (the MAML term's lr "
                             "as a fraction of POCA's), maml_step (per_task: each task's query "
                             "update steps on its own; mean: one step per minibatch on the "
                             "tasks' mean gradient), relabel_query (true: the update at "
                             "theta clips the adapted actors' query rows around theta), "
                             "query_importance (true, with relabel_query: and weighs them "
                             "by pi_theta / pi_theta'), sampling (per_task: each task "
                             "samples fresh support and query episodes; shared: theta "
                             "samples DR's batch, the tasks are its whole episodes, queries "
                             "run on a one-env side runner), "
                             "task_envs (envs each task samples on; 0: the preset's) "
                             "(e.g. --meta outer=reptile --meta reptile_lr=0.5)")


def build_parser() -> argparse.ArgumentParser:
    from rl_scan.cli.env_args import add_env_args

    fmt = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog="rl-scan", formatter_class=fmt, epilog=EXAMPLES,
        description="Multi-robot 3D scanning with RLlib: simulator, training and reports.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sc = sub.add_parser("scenario", formatter_class=fmt, help="show or export a scenario",
                        description="Show a scenario's objects, cell counts and robot starts, "
                                    "or export it as a scenario YAML or a mesh file.")
    sc_sub = sc.add_subparsers(dest="action", required=True, metavar="ACTION")
    show = sc_sub.add_parser("show", help="print objects, cells and starts")
    show.add_argument("name", help="ablation | train:N | test:N | random | a .yaml file")
    add_env_args(show, scenario=None)
    export = sc_sub.add_parser("export", help="write the scenario to .yaml or .obj/.stl/.glb/.ply")
    export.add_argument("name", help="ablation | train:N | test:N | a .yaml file")
    export.add_argument("out", help="output path; the suffix chooses the format")
    add_env_args(export, scenario=None)
    for p in (show, export):
        p.set_defaults(func=commands.scenario_cmd)

    bench = sub.add_parser("bench", formatter_class=fmt, help="benchmarks",
                           description="Benchmarks printing figures and ratios from one run.")
    bench_sub = bench.add_subparsers(dest="what", required=True, metavar="WHAT")
    benv = bench_sub.add_parser(
        "env", formatter_class=fmt, help="simulator and adapter speed, scripted-team coverage",
        description="Core simulator env steps/s (random actions, all rays), the raycast "
                    "kernel's rays/s against the measured limit, the RLlib and PettingZoo "
                    "adapters' env steps/s, peak memory, and the coverage of the greedy and "
                    "random scripted teams on the ablation and the five test scenarios. "
                    "Run it on an idle machine; it pins itself to one core.")
    benv.add_argument("--seconds", type=float, default=3.0, help="time per speed measurement")
    benv.add_argument("--seeds", type=int, default=3, help="episodes per scripted team/scene")
    benv.add_argument("--no-pin", action="store_true", help="do not pin to one CPU core")
    benv.add_argument("--json", default=None, help="also write the figures to this JSON file")
    add_env_args(benv)
    benv.set_defaults(func=commands.bench_cmd)
    btrain = bench_sub.add_parser(
        "train", formatter_class=fmt, help="training throughput: sampling, learner, end to end",
        description="For stock RLlib PPO, PPO and POCA on the fast sampler, and both with "
                    "sampling overlapped with learning (one remote runner), at the same "
                    "batch sizes (default: the quick preset's) and torch threads: env-only, "
                    "sampling-only, learner-only and end-to-end env steps/s, s/iteration, "
                    "memory (peak RSS, PSS), the learner's FLOPs per env step and "
                    "GFLOP/s beside a matmul roof measured in the same run; then the fast "
                    "sampler with 1 and 2 remote env runners; and the ratios. Run it on an "
                    "idle machine.")
    btrain.add_argument("--iterations", type=int, default=3, help="timed iterations")
    btrain.add_argument("--batch", type=int, default=4000, help="env steps per iteration")
    btrain.add_argument("--minibatch", type=int, default=1024, help="agent rows per minibatch")
    btrain.add_argument("--epochs", type=int, default=3)
    btrain.add_argument("--envs-per-runner", type=int, default=4)
    btrain.add_argument("--threads", type=int, default=1,
                        help="torch threads (default 1: what a training run's process gets "
                             "from Ray per CPU it reserves)")
    btrain.add_argument("--json", default=None, help="also write the figures to this JSON file")
    add_env_args(btrain)
    btrain.set_defaults(func=commands.bench_train_cmd)
    bmpe = bench_sub.add_parser(
        "mpe", formatter_class=fmt, help="POCA vs PPO on PettingZoo MPE simple_spread_v3",
        description="External check: train each algorithm on simple_spread_v3 (mpe2, 3 "
                    "agents, continuous actions) with the same actor size, budget and seeds, "
                    "and print the final mean episode returns.")
    bmpe.add_argument("--algos", default="ppo,poca",
                      help="comma-separated, of ppo, poca, and POCA's ablations "
                           "poca-value-baseline (advantage G - V for every agent), "
                           "poca-mean-reward (group reward = mean over agents) and "
                           "poca-joint-ratio (the joint action density's ratio is clipped)")
    bmpe.add_argument("--seeds", type=int, default=3)
    bmpe.add_argument("--env-steps", type=int, default=100_000, help="budget per run")
    bmpe.add_argument("--json", default=None, help="also write curves and figures here")
    bmpe.set_defaults(func=commands.bench_mpe_cmd)

    tr = sub.add_parser(
        "train", formatter_class=fmt, help="train POCA or PPO through Ray Tune",
        description="Train a team through Ray Tune (local by default, a Ray cluster with "
                    f"--address). Writes RESULTS/NAME/ with {RUN_FILE} (config, seed, git "
                    f"commit), {EVAL_FILE}, and {TUNE_DIR}/{TRAIN_TRIAL}/ with "
                    f"{PROGRESS_FILE}, TensorBoard events "
                    "and checkpoints; "
                    "--resume continues an interrupted run from its last checkpoint.")
    tr.add_argument("--algo", choices=tuple(ALGORITHMS), default="poca",
                    help="; ".join(f"{a.name}: {a.summary}" for a in ALGORITHMS.values())
                    + " (default poca)")
    _add_run_args(tr, "ALGO_SCENARIO_PRESET_sSEED")
    tr.add_argument("--total-env-steps", type=int, default=None, help="override the budget")
    tr.add_argument("--init-from", default=None, metavar="CHECKPOINT",
                    help="start from this checkpoint's (or run folder's) weights")
    add_env_args(tr)
    tr.set_defaults(func=commands.train_cmd)

    mt = sub.add_parser(
        "meta-train", formatter_class=fmt, help="meta-train MetaPOCA (meta-MRSS) through Tune",
        description="Meta-train POCA with first-order MAML (the paper's Algorithm 1): per "
                    "meta-iteration `tasks` train scenarios; for each, support_steps env "
                    "steps with the meta policy, one ordinary POCA update on them (the "
                    "adaptation), query_steps env steps with the adapted policy; then the "
                    "outer update learns from every step (support at the meta weights, "
                    "query at the adapted ones; the critic learns at the meta weights "
                    "only, where the tasks are mixed). Same run folder, --resume and "
                    "checkpoints as `train`; --scenario is what evaluation uses.")
    _add_run_args(mt, "meta-poca_SCENARIO_PRESET_sSEED")
    mt.add_argument("--total-env-steps", type=int, default=None, help="override the budget")
    _add_meta_arg(mt)
    mt.add_argument("--init-from", default=None, metavar="CHECKPOINT",
                    help="warm start from this checkpoint's (or run folder's) weights, "
                         "e.g. a domain-randomisation run")
    add_env_args(mt)
    mt.set_defaults(func=commands.train_cmd, algo="meta-poca")

    ad = sub.add_parser(
        "adapt", formatter_class=fmt, help="adapt a trained team to a scenario (POCA)",
        description="Fine-tune a checkpoint's team (meta-trained or not) with POCA on a "
                    "scenario for a budget of env steps, evaluating on the way; a normal run "
                    f"folder whose {EVAL_FILE} is the adaptation curve.")
    ad.add_argument("checkpoint", help="a checkpoint, trial or run folder (newest checkpoint)")
    ad.add_argument("--budget", type=int, default=None,
                    help="adaptation env steps (default: the preset's budget)")
    _add_run_args(ad, "poca_SCENARIO_PRESET_sSEED")
    add_env_args(ad)
    ad.set_defaults(func=commands.adapt_cmd, total_env_steps=None)

    ab = sub.add_parser(
        "ablate", formatter_class=fmt, help="ablation studies (Tune + Optuna)",
        description="Run one of the paper's ablations as a Ray Tune study searched by "
                    "Optuna, every trial a real training run with evaluation and "
                    "checkpoints: " + "; ".join(f"{s.name} ({s.summary})"
                                                for s in STUDIES.values())
                    + ". Studies with conditions run the full grid x seeds. The Optuna "
                    "study is stored in SQLite in the study folder; --resume continues an "
                    "interrupted study.")
    ab.add_argument("study", choices=tuple(STUDIES))
    _add_run_args(ab, "ablate-STUDY-PRESET")
    ab.add_argument("--seeds", type=int, default=3, help="seeds per condition (grid studies)")
    ab.add_argument("--trials", type=int, default=8,
                    help="trials of a search study (hpo); grid studies run condition x seed")
    ab.add_argument("--conditions", default=None, metavar="A,B",
                    help="run only these conditions of a grid study (default: all), e.g. "
                         "reward --conditions poca/team,ppo/team or team --conditions "
                         "2,2,0,4")
    ab.add_argument("--total-env-steps", type=int, default=None, help="override the budget")
    add_env_args(ab)
    ab.set_defaults(func=commands.ablate_cmd)

    rl = sub.add_parser(
        "replay", formatter_class=fmt, help="interactive 3D HTML replay of an episode",
        description="Play one evaluation episode with a run's team (sampled actions, as "
                    "evaluation does) or, without RUN_DIR, the scripted greedy team, and "
                    "write a self-contained plotly HTML: cells turning from green to blue "
                    "as they are scanned, robot paths, a slider and a play button.")
    rl.add_argument("run", nargs="?", default=None,
                    help="a run, trial or checkpoint folder (default: the greedy team)")
    rl.add_argument("--out", default="replay.html", help="output .html")
    rl.add_argument("--every", type=int, default=5, help="one frame every N env steps")
    rl.add_argument("--seed", type=int, default=0, help="reset seed")
    add_env_args(rl)
    rl.set_defaults(func=commands.replay_cmd)

    rp = sub.add_parser(
        "report", formatter_class=fmt, help="Markdown + HTML report of a results folder",
        description="Read every run, ablation study and meta-MRSS experiment under "
                    "RESULTS_DIR (finished or not) and write report.md, a self-contained "
                    "report.html, figures/*.png and marl_eval.json (marl-eval's layout) to "
                    "OUT (default RESULTS_DIR/report).")
    rp.add_argument("results_dir")
    rp.add_argument("--out", default=None, help="output folder (default RESULTS_DIR/report)")
    rp.add_argument("--no-reference", action="store_true",
                    help="skip the scripted greedy team's reference line")
    rp.add_argument("--compare", default=None, metavar="REPORT",
                    help="an earlier report (its folder or marl_eval.json, e.g. a committed "
                         "example): its runs are drawn and tabled beside these, each condition "
                         "compared with its namesake")
    rp.add_argument("--add", action="append", default=[], metavar="FOLDER",
                    help="a results folder or an earlier report's folder (its runs.json) "
                         "whose runs join these as the same study (repeatable): a study "
                         "run in parts, e.g. other seeds in another session under the same "
                         "--name, reports as one; a run in RESULTS_DIR replaces its "
                         "namesake (same study, condition and seed)")
    rp.set_defaults(func=commands.report_cmd)

    ex = sub.add_parser("experiment", formatter_class=fmt, help="multi-run protocols",
                        description="Protocols made of many runs.")
    ex_sub = ex.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    mm = ex_sub.add_parser(
        "meta-mrss", formatter_class=fmt, help="meta-MRSS vs its baselines on test scenes",
        description="Pre-train meta-MRSS, domain randomisation and transfer learning, then "
                    "adapt each (and standard POCA from scratch) on every held-out test "
                    "scenario with the same budget, for each seed; print method x (final "
                    "coverage, env steps to 80 %, success) with the paper's figures. "
                    "Independent runs go in parallel (--jobs; the default fills the Ray "
                    "cluster's CPUs). Re-running resumes: finished runs are skipped, "
                    "interrupted ones continue from their last checkpoint.")
    mm.add_argument("--preset", choices=tuple(PROTOCOLS), default="quick",
                    help="env steps of pre-training + adaptation per run: " + ", ".join(
                        f"{name} {p.pretrain_steps:,} + {p.adapt_steps:,}"
                        for name, p in PROTOCOLS.items()))
    mm.add_argument("--seeds", type=int, default=3, help="seeds per method and test scene")
    mm.add_argument("--seed", type=int, default=0,
                    help="the first seed (seeds SEED .. SEED+SEEDS-1): a protocol longer than "
                         "one sitting runs a seed at a time, e.g. --seed 1 --seeds 1, and "
                         "`rl-scan report RESULTS --add EARLIER` joins the parts")
    mm.add_argument("--tests", default="0,1,2,3,4", help="test scenario indices (0-4)")
    mm.add_argument("--methods", default="meta-mrss,dr,transfer,poca",
                    help="comma-separated subset of meta-mrss,dr,transfer,poca")
    mm.add_argument("--pretrain-steps", type=int, default=None, help="override the preset")
    mm.add_argument("--adapt-steps", type=int, default=None, help="override the preset")
    mm.add_argument("--jobs", type=int, default=None,
                    help="runs at once (default: as many as the Ray cluster's CPUs hold)")
    mm.add_argument("--address", default=None, help="Ray cluster address (default: local)")
    mm.add_argument("--results", default="results")
    mm.add_argument("--name", default="meta-mrss")
    _add_meta_arg(mm)
    _add_sampler_arg(mm)
    _add_resources_arg(mm)
    mm.set_defaults(func=commands.experiment_cmd)

    hm = ex_sub.add_parser(
        "hetero-map", formatter_class=fmt,
        help="where 2 wheeled + 2 quads beat a homogeneous team (scripted greedy team)",
        description="An Optuna study (SQLite in the study folder) over the simulator's "
                    "assumed parameters that the paper leaves open: the wheeled sensor's "
                    "elevations (fan or sphere), quad speed and sensor range, and a quad "
                    "flight-time budget. At each of the 32 grid points the scripted greedy "
                    "team plays the same train scenes as 2 + 2, 0 + 4 and 4 + 0; the point's "
                    "value is mixed minus best homogeneous coverage. Re-running resumes "
                    "(finished points are kept); `rl-scan report` draws the map. To train "
                    "a point, run `rl-scan ablate team` with the point's settings as --set "
                    "(wheeled.elevations, quad.max_speed, quad.sensor_range, "
                    "quad_flight_time) into the same results folder: the report marks every "
                    "team study whose settings are a point's on the map.")
    hm.add_argument("--scenes", type=int, default=8,
                    help="train scenes (train:0 ..) each team plays at every point")
    hm.add_argument("--results", default="results")
    hm.add_argument("--name", default="hetero-map")
    hm.add_argument("--resume", action="store_true", help="continue the study named --name")
    hm.set_defaults(func=commands.hetero_map_cmd)

    ev = sub.add_parser(
        "evaluate", formatter_class=fmt, help="metrics of a trained team",
        description="Play episodes with a checkpoint's policies (sampled actions) on its run's "
                    "env config, or on the scenario/team given here, and print coverage, "
                    "success, steps to 50/80/95 %, collisions and returns per kind, beside "
                    "the scripted greedy team.")
    ev.add_argument("checkpoint", help="a checkpoint, trial or run folder (newest checkpoint)")
    ev.add_argument("--best", action="store_true",
                    help="use the run's best kept checkpoint (by its training-time evaluation) "
                         f"and record the result in {BEST_EVAL_FILE} in the run folder, where "
                         "`rl-scan report` shows it as a secondary, selection-biased number")
    ev.add_argument("--episodes", type=int, default=10)
    ev.add_argument("--seed", type=int, default=0, help="reset seed of the first episode")
    ev.add_argument("--deterministic", action="store_true",
                    help="act with the policy mean instead of sampling (training evaluates "
                         "sampled actions, as ML-Agents does)")
    ev.add_argument("--no-reference", action="store_true", help="skip the greedy team")
    ev.add_argument("--json", default=None, help="also write per-episode metrics here")
    add_env_args(ev)
    ev.set_defaults(func=commands.evaluate_cmd)

    render = sub.add_parser("render", formatter_class=fmt, help="PNG/GIF of an episode",
                            description="Play one episode with a checkpoint's team (if given) "
                                        "or a scripted team and write a GIF (every N-th step) "
                                        "or a PNG of the last frame.")
    render.add_argument("checkpoint", nargs="?", default=None,
                        help="a checkpoint, trial or run folder (default: a scripted team)")
    render.add_argument("--policy", choices=("greedy", "random"), default="greedy",
                        help="scripted team to play (default greedy)")
    render.add_argument("--out", default="render.gif", help="output .gif or .png")
    render.add_argument("--every", type=int, default=5, help="keep every N-th step in a GIF")
    render.add_argument("--fps", type=int, default=10, help="GIF frames per second")
    render.add_argument("--seed", type=int, default=0, help="reset seed")
    add_env_args(render)
    render.set_defaults(func=commands.render_cmd)
    for leaf in _leaves(parser):
        leaf.add_argument("--verbose", action="store_true",
                          help="also show Ray's own log lines (hidden by default)")
    return parser


def _leaves(parser: argparse.ArgumentParser):
    """The parsers of every runnable command (sub-commands of sub-commands included)."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield parser
    for action in subs:
        for child in dict.fromkeys(action.choices.values()):
            yield from _leaves(child)
