"""The ``rl-scan`` command line.

  rl-scan scenario show NAME        objects, cell counts and robot starts of a scenario
  rl-scan scenario export NAME OUT  write a scenario as YAML (re-loadable) or a mesh file
  rl-scan bench env                 simulator/adapter speed and scripted-team coverage
  rl-scan render                    PNG/GIF of an episode of the scripted greedy team
  rl-scan train                     train POCA or PPO through Ray Tune
  rl-scan evaluate CHECKPOINT       metrics table of a trained team

Errors in the input (unknown keys, bad values, missing files) print one line naming the
field and exit with status 2 before anything runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rl_scan.config import ConfigError, to_dict
from rl_scan.metrics import BEST_EVAL_FILE, EVAL_FILE

EXAMPLES = """examples:
  rl-scan scenario show ablation
  rl-scan scenario show test:3 --team 1,3
  rl-scan scenario export train:12 scene.yaml
  rl-scan bench env --seconds 3
  rl-scan render --scenario test:0 --out runs/test0.gif --every 5
  rl-scan train --algo ppo --preset smoke --scenario ablation
"""


def _write_json(path: str, data) -> None:
    """Write figures as JSON (NaN/numpy values as floats) and say where."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=1, default=float))
    print(f"wrote {path}")


def _scenario_cmd(args: argparse.Namespace) -> int:
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    from rl_scan.env_args import env_config_from_args
    from rl_scan.envs.core import ScanCore

    args.scenario = args.name
    config = env_config_from_args(args)
    core = ScanCore(config)
    core.reset(seed=0)  # for 'random', this draw is the one shown/exported
    world = core.world
    scenario = world.scenario
    if args.action == "export":
        return _export(world, Path(args.out))
    console = Console()
    table = Table(title=f"scenario {scenario.name!r}: {world.n_objects} objects, "
                        f"{world.n_cells} cells (arena {' x '.join(f'{a:g}' for a in config.arena)}"
                        f" m, cell {config.cell_size} m)")
    for col in ("#", "shape", "size m (x,y,z)", "position m (x,y)", "yaw", "voxels", "cells"):
        table.add_column(col, justify="left" if col == "shape" else "right")
    voxels = np.bincount(world.object_id[world.object_id >= 0], minlength=world.n_objects)
    for i, o in enumerate(scenario.objects):
        table.add_row(str(i), o.shape, ", ".join(f"{s:g}" for s in o.size),
                      ", ".join(f"{p:g}" for p in o.position), f"{o.yaw:g}",
                      str(voxels[i]), str(world.obj_total[i]))
    console.print(table)
    starts = Table(title="robot starts (seed 0; jitter "
                         f"{config.start_jitter} m per reset)")
    for col in ("agent", "x", "y", "z"):
        starts.add_column(col, justify="right")
    for aid, p in zip(world.agent_ids, world.pos):
        starts.add_row(aid, *(f"{v:.2f}" for v in p))
    console.print(starts)
    return 0


def _export(world, out: Path) -> int:
    import yaml

    suffix = out.suffix.lower()
    out.parent.mkdir(parents=True, exist_ok=True)
    if suffix in (".yaml", ".yml"):
        data = {"name": world.scenario.name,
                "objects": [_object_fields(o) for o in world.scenario.objects],
                "starts": [list(s) for s in world.scenario.starts]}
        out.write_text(yaml.safe_dump(data, sort_keys=False, default_flow_style=None))
    elif suffix in (".obj", ".stl", ".glb", ".ply"):
        import trimesh

        from rl_scan.envs.sim.objects import placed_parts

        parts = [m for o in world.scenario.objects for m in placed_parts(o)]
        trimesh.util.concatenate(parts).export(out)
    else:
        raise ConfigError(f"out={str(out)!r} is invalid: allowed a .yaml, .obj, .stl, .glb "
                          "or .ply path")
    print(f"wrote {out}")
    return 0


def _object_fields(spec) -> dict:
    """The fields of an ObjectSpec that matter for its shape (for a readable YAML)."""
    keep = {"shape", "size", "position", "z", "yaw"} | {
        "lshape": {"proportions"}, "hull": {"points"}, "mesh": {"path"}}.get(spec.shape, set())
    return {k: v for k, v in to_dict(spec).items() if k in keep}


def _bench_cmd(args: argparse.Namespace) -> int:
    from rl_scan.bench import run_bench_env
    from rl_scan.env_args import env_config_from_args

    if args.seconds <= 0:
        raise ConfigError(f"seconds={args.seconds} is invalid: allowed a value > 0")
    if args.seeds < 1:
        raise ConfigError(f"seeds={args.seeds} is invalid: allowed an integer >= 1")
    config = env_config_from_args(args)
    res = run_bench_env(config, seconds=args.seconds, seeds=args.seeds,
                        pin_core=not args.no_pin)
    if args.json:
        _write_json(args.json, res)
    return 0


def _parse_algos(text: str, allowed) -> list[str]:
    """'ppo,poca' -> ['ppo', 'poca'], each one of ``allowed``."""
    algos = [a.strip() for a in text.split(",") if a.strip()]
    if not algos or any(a not in allowed for a in algos):
        raise ConfigError(f"algos={text!r} is invalid: allowed a comma-separated list of "
                          f"{sorted(allowed)}")
    return algos


def _bench_train_cmd(args: argparse.Namespace) -> int:
    from rl_scan.bench_train import run_bench_train
    from rl_scan.env_args import env_config_from_args, env_mapping_from_args
    from rl_scan.tuning.launch import ALGORITHMS

    algos = _parse_algos(args.algos, ALGORITHMS)
    for name in ("iterations", "batch", "minibatch", "epochs", "envs_per_runner"):
        if getattr(args, name) < 1:
            raise ConfigError(f"{name}={getattr(args, name)} is invalid: allowed an integer >= 1")
    env_config_from_args(args)
    res = run_bench_train(env_mapping_from_args(args), algos, iterations=args.iterations,
                          train_batch_size=args.batch, minibatch_size=args.minibatch,
                          num_epochs=args.epochs, envs_per_runner=args.envs_per_runner)
    if args.json:
        _write_json(args.json, res)
    return 0


def _bench_mpe_cmd(args: argparse.Namespace) -> int:
    from rl_scan.bench_mpe import run_bench_mpe

    algos = _parse_algos(args.algos, ("poca", "ppo"))
    for name in ("seeds", "env_steps"):
        if getattr(args, name) < 1:
            raise ConfigError(f"{name}={getattr(args, name)} is invalid: allowed an integer >= 1")
    res = run_bench_mpe(algos, args.seeds, args.env_steps)
    if args.json:
        _write_json(args.json, res)
    return 0


def _render_cmd(args: argparse.Namespace) -> int:
    from rl_scan.env_args import env_config_from_args
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.heuristics import GreedyTeam, RandomTeam, run_episode
    from rl_scan.envs.render import save_frames

    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".gif"):
        raise ConfigError(f"out={str(out)!r} is invalid: allowed a .png or .gif path")
    if args.every < 1:
        raise ConfigError(f"every={args.every} is invalid: allowed an integer >= 1")
    if args.checkpoint:
        core, team, label = _checkpoint_team(args)
    else:
        core = ScanCore(env_config_from_args(args))
        team = GreedyTeam(core) if args.policy == "greedy" else RandomTeam(core, seed=args.seed)
        label = f"{args.policy} team"
    frames: list = []
    metrics = run_episode(core, team, seed=args.seed, frames=frames, frame_every=args.every)
    save_frames(frames, out, fps=args.fps)
    print(f"wrote {out} ({len(frames) if out.suffix.lower() == '.gif' else 1} frames): "
          f"{label}, coverage {100 * metrics['coverage']:.1f}% in "
          f"{metrics['episode_steps']:.0f} steps, {metrics['collisions']:.0f} collisions")
    return 0


def _replay_cmd(args: argparse.Namespace) -> int:
    from rl_scan.env_args import env_config_from_args
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.heuristics import GreedyTeam
    from rl_scan.reports.replay import record_episode, write_replay

    out = Path(args.out)
    if out.suffix.lower() != ".html":
        raise ConfigError(f"out={str(out)!r} is invalid: allowed an .html path")
    if args.every < 1:
        raise ConfigError(f"every={args.every} is invalid: allowed an integer >= 1")
    if args.run:
        core, team, label = _checkpoint_team(args)
    else:
        core = ScanCore(env_config_from_args(args))
        team, label = GreedyTeam(core), "greedy team"
    rec = record_episode(core, team, seed=args.seed)
    write_replay(rec, out, every=args.every, title=f"{label} on {core.config.scenario}:")
    print(f"wrote {out}: {label}, coverage {100 * rec.metrics['coverage']:.1f}% in "
          f"{len(rec.paths) - 1} steps")
    return 0


def _checkpoint_team(args: argparse.Namespace):
    """ScanCore on the run's env config (flags override it) and the checkpoint's team."""
    from rl_scan.algorithms.rollout import (
        PolicyTeam,
        load_actors,
        resolve_checkpoint,
        run_env_config,
    )
    from rl_scan.config import deep_merge
    from rl_scan.env_args import env_mapping_from_args
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.sim.env_config import make_env_config

    target = getattr(args, "checkpoint", None) or args.run
    if getattr(args, "best", False):
        from rl_scan.algorithms.rollout import best_checkpoint

        ckpt, args.best_info = best_checkpoint(target)
    else:
        ckpt = resolve_checkpoint(target)
    config = make_env_config(deep_merge(run_env_config(ckpt), env_mapping_from_args(args)))
    core = ScanCore(config)
    import torch

    torch.manual_seed(getattr(args, "seed", 0))  # sampled actions are reproducible
    team = PolicyTeam(load_actors(ckpt), explore=not getattr(args, "deterministic", False))
    return core, team, f"checkpoint {ckpt}"


def _evaluate_cmd(args: argparse.Namespace) -> int:
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    from rl_scan import metrics as M
    from rl_scan.envs.heuristics import GreedyTeam, run_episode

    if args.episodes < 1:
        raise ConfigError(f"episodes={args.episodes} is invalid: allowed an integer >= 1")
    core, team, label = _checkpoint_team(args)
    runs = [run_episode(core, team, seed=args.seed + i) for i in range(args.episodes)]
    greedy = [run_episode(core, GreedyTeam(core), seed=args.seed + i)
              for i in range(args.episodes)] if not args.no_reference else []
    table = Table(title=f"{label}\non {core.scenario_name}, {args.episodes} episodes "
                        f"({'mean' if args.deterministic else 'sampled'} actions)")
    for col in ("metric", "mean", "std", "min", "max", "greedy team mean"):
        table.add_column(col, justify="left" if col == "metric" else "right")
    summary = {}
    for key in M.EPISODE_METRICS:
        vals = np.array([r[key] for r in runs], dtype=float)
        ok = vals[~np.isnan(vals)]
        summary[key] = {"mean": float(ok.mean()) if len(ok) else None,
                        "std": float(ok.std()) if len(ok) else None, "n": int(len(ok))}
        ref_vals = np.array([g[key] for g in greedy], dtype=float)
        ref_vals = ref_vals[~np.isnan(ref_vals)]
        ref = ref_vals.mean() if len(ref_vals) else float("nan")
        cells = [f"{f(ok):.3f}" if len(ok) else "-" for f in (np.mean, np.std, np.min, np.max)]
        table.add_row(key + ("" if len(ok) == len(vals) else f" ({len(ok)}/{len(vals)} reached)"),
                      *cells, "-" if np.isnan(ref) else f"{ref:.3f}")
    Console().print(table)
    if args.json:
        _write_json(args.json, {"checkpoint": label, "episodes": runs, "summary": summary})
    if args.best:
        _record_best_eval(core, label, args, runs)
    return 0


def _record_best_eval(core, label: str, args: argparse.Namespace, runs: list[dict]) -> None:
    """Write best_checkpoint_eval.json beside the run's eval_metrics.json (for the report)."""
    ckpt = Path(label.removeprefix("checkpoint "))
    folder = next((p for p in ckpt.parents if (p / EVAL_FILE).is_file()), None)
    if folder is None:
        print(f"note: no {EVAL_FILE} above {ckpt}; nothing recorded for the report")
        return
    out = folder / BEST_EVAL_FILE
    _write_json(str(out), {**args.best_info, "checkpoint": str(ckpt),
                           "scenario": core.scenario_name, "episodes": len(runs),
                           "seed": args.seed, "deterministic": args.deterministic,
                           "coverage": [r["coverage"] for r in runs],
                           "success": [r["success"] for r in runs]})
    print(f"best checkpoint (iteration {args.best_info['training_iteration']}, training-time "
          f"eval {args.best_info['eval_coverage']:.3f}) recorded in {out}")


def _train_cmd(args: argparse.Namespace) -> int:
    from rl_scan.env_args import env_config_from_args, env_mapping_from_args
    from rl_scan.tuning.launch import train

    overrides = {k: v for k, v in (("num_env_runners", args.num_env_runners),
                                   ("num_envs_per_env_runner", args.envs_per_runner),
                                   ("total_env_steps", args.total_env_steps)) if v is not None}
    env_config_from_args(args)  # validate before anything starts
    run_dir = train(args.algo, env_mapping_from_args(args), args.preset, seed=args.seed,
                    results_dir=args.results, name=args.name, address=args.address,
                    resume=args.resume, preset_overrides=overrides,
                    init_from=getattr(args, "init_from", None))
    print(f"done: {run_dir}")
    return 0


def _adapt_cmd(args: argparse.Namespace) -> int:
    args.algo, args.init_from = "poca", args.checkpoint
    if args.budget is not None:
        if args.budget < 1:
            raise ConfigError(f"budget={args.budget} is invalid: allowed >= 1 env steps")
        args.total_env_steps = args.budget
    return _train_cmd(args)


def _experiment_cmd(args: argparse.Namespace) -> int:
    from rl_scan.tuning.meta_mrss import parse_tests, run_protocol

    overrides = {k: v for k, v in (("pretrain_steps", args.pretrain_steps),
                                   ("adapt_steps", args.adapt_steps)) if v is not None}
    run_protocol(args.results, args.name, preset=args.preset,
                 methods=[m.strip() for m in args.methods.split(",") if m.strip()],
                 tests=parse_tests(args.tests), seeds=args.seeds,
                 protocol_overrides=overrides)
    return 0


def _ablate_cmd(args: argparse.Namespace) -> int:
    from rl_scan.env_args import env_config_from_args, env_mapping_from_args
    from rl_scan.tuning.ablate import ablate

    env_config_from_args(args)
    overrides = {k: v for k, v in (("num_env_runners", args.num_env_runners),
                                   ("total_env_steps", args.total_env_steps)) if v is not None}
    folder = ablate(args.study, args.preset, seeds=args.seeds, trials=args.trials,
                    results_dir=args.results, name=args.name, address=args.address,
                    resume=args.resume, env_config=env_mapping_from_args(args),
                    preset_overrides=overrides)
    print(f"done: {folder}  (optuna-dashboard sqlite:///{folder / 'optuna.db'})")
    return 0


def _report_cmd(args: argparse.Namespace) -> int:
    from rl_scan.reports.build import build_report

    out = build_report(args.results_dir, args.out, reference=not args.no_reference)
    print(f"wrote {out / 'report.md'}, {out / 'report.html'}, {out / 'marl_eval.json'}")
    return 0


def _add_run_args(p: argparse.ArgumentParser, default_name: str) -> None:
    """Options every Tune-launched run shares (train, meta-train, adapt)."""
    p.add_argument("--preset", choices=("smoke", "quick", "paper"), default="quick",
                   help="budget: smoke (seconds), quick (minutes, default), paper (cluster)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--results", default="results", help="results folder (default results/)")
    p.add_argument("--name", default=None, help=f"run name (default {default_name})")
    p.add_argument("--address", default=None, help="Ray cluster address (default: local)")
    p.add_argument("--resume", action="store_true", help="continue the run named --name")
    p.add_argument("--num-env-runners", type=int, default=None,
                   help="remote sampling actors (preset default; each needs a CPU)")
    p.add_argument("--envs-per-runner", type=int, default=None, help="envs per env runner")


def build_parser() -> argparse.ArgumentParser:
    from rl_scan.env_args import add_env_args

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
        p.set_defaults(func=_scenario_cmd)

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
    benv.set_defaults(func=_bench_cmd)
    btrain = bench_sub.add_parser(
        "train", formatter_class=fmt, help="end-to-end training throughput",
        description="Env steps/s of train() (sampling + learning) for each algorithm on the "
                    "same env and batch sizes with 0 env runners, and for the first "
                    "algorithm with 1 and 2 env runners; peak RSS of the Ray process tree.")
    btrain.add_argument("--algos", default="ppo,poca",
                        help="comma-separated algorithms; the first is the reference")
    btrain.add_argument("--iterations", type=int, default=3, help="timed train() calls")
    btrain.add_argument("--batch", type=int, default=2000, help="env steps per iteration")
    btrain.add_argument("--minibatch", type=int, default=512, help="agent rows per minibatch")
    btrain.add_argument("--epochs", type=int, default=3)
    btrain.add_argument("--envs-per-runner", type=int, default=4)
    btrain.add_argument("--json", default=None, help="also write the figures to this JSON file")
    add_env_args(btrain)
    btrain.set_defaults(func=_bench_train_cmd)
    bmpe = bench_sub.add_parser(
        "mpe", formatter_class=fmt, help="POCA vs PPO on PettingZoo MPE simple_spread_v3",
        description="External check: train each algorithm on simple_spread_v3 (mpe2, 3 "
                    "agents, continuous actions) with the same actor size, budget and seeds, "
                    "and print the final mean episode returns.")
    bmpe.add_argument("--algos", default="ppo,poca", help="comma-separated algorithms")
    bmpe.add_argument("--seeds", type=int, default=3)
    bmpe.add_argument("--env-steps", type=int, default=100_000, help="budget per run")
    bmpe.add_argument("--json", default=None, help="also write curves and figures here")
    bmpe.set_defaults(func=_bench_mpe_cmd)

    tr = sub.add_parser(
        "train", formatter_class=fmt, help="train POCA or PPO through Ray Tune",
        description="Train a team through Ray Tune (local by default, a Ray cluster with "
                    "--address). Writes RESULTS/NAME/ with run.yaml (config, seed, git commit), "
                    "eval_metrics.json, and tune/trial/ with progress.csv, TensorBoard events "
                    "and checkpoints; "
                    "--resume continues an interrupted run from its last checkpoint.")
    tr.add_argument("--algo", choices=("poca", "ppo", "meta-poca"), default="poca",
                    help="default poca")
    _add_run_args(tr, "ALGO_SCENARIO_PRESET_sSEED")
    tr.add_argument("--total-env-steps", type=int, default=None, help="override the budget")
    tr.add_argument("--init-from", default=None, metavar="CHECKPOINT",
                    help="start from this checkpoint's (or run folder's) weights")
    add_env_args(tr)
    tr.set_defaults(func=_train_cmd)

    mt = sub.add_parser(
        "meta-train", formatter_class=fmt, help="meta-train MetaPOCA (meta-MRSS) through Tune",
        description="Meta-train POCA with MAML (the paper's Algorithm 1): per meta-iteration "
                    "the preset's meta_tasks train scenarios, meta_episodes support episodes "
                    "each, inner_steps adaptation steps (first order, inner Adam), as many "
                    "query episodes, one meta update. Same run folder, --resume and "
                    "checkpoints as `train`; --scenario is what evaluation uses.")
    _add_run_args(mt, "meta-poca_SCENARIO_PRESET_sSEED")
    mt.add_argument("--total-env-steps", type=int, default=None, help="override the budget")
    add_env_args(mt)
    mt.set_defaults(func=_train_cmd, algo="meta-poca")

    ad = sub.add_parser(
        "adapt", formatter_class=fmt, help="adapt a trained team to a scenario (POCA)",
        description="Fine-tune a checkpoint's team (meta-trained or not) with POCA on a "
                    "scenario for a budget of env steps, evaluating on the way; a normal run "
                    "folder whose eval_metrics.json is the adaptation curve.")
    ad.add_argument("checkpoint", help="a checkpoint, trial or run folder (newest checkpoint)")
    ad.add_argument("--budget", type=int, default=None,
                    help="adaptation env steps (default: the preset's budget)")
    _add_run_args(ad, "poca_SCENARIO_PRESET_sSEED")
    add_env_args(ad)
    ad.set_defaults(func=_adapt_cmd, total_env_steps=None)

    ab = sub.add_parser(
        "ablate", formatter_class=fmt, help="ablation studies (Tune + Optuna)",
        description="Run one of the paper's ablations as a Ray Tune study searched by "
                    "Optuna, every trial a real training run with evaluation and "
                    "checkpoints: comm (Table II's 7 schemes + scheme 1 without object "
                    "information), algo (POCA vs PPO), team (2+2 vs 4 quads vs 4 wheeled), "
                    "hpo (TPE over POCA's lr, entropy, lambda, epochs). Categorical studies "
                    "run the full grid x seeds. The Optuna study is stored in SQLite in the "
                    "study folder; --resume continues an interrupted study.")
    ab.add_argument("study", choices=("comm", "algo", "team", "hpo"))
    _add_run_args(ab, "ablate-STUDY-PRESET")
    ab.add_argument("--seeds", type=int, default=3, help="seeds per condition (grid studies)")
    ab.add_argument("--trials", type=int, default=8, help="trials of the hpo study")
    ab.add_argument("--total-env-steps", type=int, default=None, help="override the budget")
    add_env_args(ab)
    ab.set_defaults(func=_ablate_cmd)

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
    rl.set_defaults(func=_replay_cmd)

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
    rp.set_defaults(func=_report_cmd)

    ex = sub.add_parser("experiment", formatter_class=fmt, help="multi-run protocols",
                        description="Protocols made of many runs.")
    ex_sub = ex.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    mm = ex_sub.add_parser(
        "meta-mrss", formatter_class=fmt, help="meta-MRSS vs its baselines on test scenes",
        description="Pre-train meta-MRSS, domain randomisation and transfer learning, then "
                    "adapt each (and standard POCA from scratch) on every held-out test "
                    "scenario with the same budget, for each seed; print method x (final "
                    "coverage, env steps to 80 %%, success) with the paper's figures. "
                    "Re-running resumes: finished runs are skipped.")
    mm.add_argument("--preset", choices=("smoke", "quick", "paper"), default="quick")
    mm.add_argument("--seeds", type=int, default=3)
    mm.add_argument("--tests", default="0,1,2,3,4", help="test scenario indices (0-4)")
    mm.add_argument("--methods", default="meta-mrss,dr,transfer,poca",
                    help="comma-separated subset of meta-mrss,dr,transfer,poca")
    mm.add_argument("--pretrain-steps", type=int, default=None, help="override the preset")
    mm.add_argument("--adapt-steps", type=int, default=None, help="override the preset")
    mm.add_argument("--results", default="results")
    mm.add_argument("--name", default="meta-mrss")
    mm.set_defaults(func=_experiment_cmd)

    ev = sub.add_parser(
        "evaluate", formatter_class=fmt, help="metrics of a trained team",
        description="Play episodes with a checkpoint's policies (sampled actions) on its run's "
                    "env config, or on the scenario/team given here, and print coverage, "
                    "success, steps to 50/80/95 %%, collisions and returns per kind, beside "
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
    ev.set_defaults(func=_evaluate_cmd)

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
    render.set_defaults(func=_render_cmd)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    ray_was_up = _ray_is_up()
    try:
        return args.func(args)
    except (ConfigError, ValueError) as e:
        print(f"rl-scan {args.command}: error: {e}", file=sys.stderr)
        return 2
    finally:
        if not ray_was_up and _ray_is_up():
            # A command that started Ray stops it, so in-process callers (notebooks, tests)
            # can start their own Ray afterwards ("ray.init twice" otherwise).
            import ray

            ray.shutdown()


def _ray_is_up() -> bool:
    """Whether Ray is initialised in this process, without importing Ray if nothing did."""
    ray = sys.modules.get("ray")
    return ray is not None and ray.is_initialized()


if __name__ == "__main__":
    sys.exit(main())
