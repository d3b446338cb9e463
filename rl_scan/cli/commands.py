"""What each ``rl-scan`` command does; ``cli.py`` holds the parser that dispatches here.

Heavy imports (Ray, torch, plotting) stay inside the commands so ``--help`` is instant.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from rl_scan.config import ConfigError, to_dict
from rl_scan.results import BEST_EVAL_FILE, OPTUNA_DB, run_dir_of


def _write_json(path: str, data) -> None:
    """Write figures as JSON (NaN/numpy values as floats) and say where."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=1, default=float))
    print(f"wrote {path}")


def scenario_cmd(args: argparse.Namespace) -> int:
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    from rl_scan.cli.env_args import env_config_from_args
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


def bench_cmd(args: argparse.Namespace) -> int:
    from rl_scan.cli.bench_env import run_bench_env
    from rl_scan.cli.env_args import env_config_from_args

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


def bench_train_cmd(args: argparse.Namespace) -> int:
    from rl_scan.cli.bench_train import run_bench_train
    from rl_scan.cli.env_args import env_config_from_args

    for name in ("iterations", "batch", "minibatch", "epochs", "envs_per_runner"):
        if getattr(args, name) < 1:
            raise ConfigError(f"{name}={getattr(args, name)} is invalid: allowed an integer >= 1")
    if args.threads < 1:
        raise ConfigError(f"threads={args.threads} is invalid: allowed an integer >= 1")
    res = run_bench_train(env_config_from_args(args), iterations=args.iterations,
                          batch=args.batch, minibatch=args.minibatch, epochs=args.epochs,
                          envs_per_runner=args.envs_per_runner, threads=args.threads)
    if args.json:
        _write_json(args.json, res)
    return 0


def bench_mpe_cmd(args: argparse.Namespace) -> int:
    from rl_scan.cli.bench_mpe import ALGOS, run_bench_mpe

    algos = _parse_algos(args.algos, tuple(ALGOS))
    for name in ("seeds", "env_steps"):
        if getattr(args, name) < 1:
            raise ConfigError(f"{name}={getattr(args, name)} is invalid: allowed an integer >= 1")
    res = run_bench_mpe(algos, args.seeds, args.env_steps)
    if args.json:
        _write_json(args.json, res)
    return 0


def render_cmd(args: argparse.Namespace) -> int:
    from rl_scan.envs.episode import run_episode
    from rl_scan.envs.render import save_frames

    out = _episode_output(args, (".png", ".gif"))
    core, team, label = _episode_team(args, args.checkpoint, args.policy)
    frames: list = []
    metrics = run_episode(core, team, seed=args.seed, frames=frames, frame_every=args.every)
    save_frames(frames, out, fps=args.fps)
    print(f"wrote {out} ({len(frames) if out.suffix.lower() == '.gif' else 1} frames): "
          f"{label}, coverage {100 * metrics['coverage']:.1f}% in "
          f"{metrics['episode_steps']:.0f} steps, {metrics['collisions']:.0f} collisions")
    return 0


def replay_cmd(args: argparse.Namespace) -> int:
    from rl_scan.reports.replay import record_episode, write_replay

    out = _episode_output(args, (".html",))
    core, team, label = _episode_team(args, args.run, "greedy")
    rec = record_episode(core, team, seed=args.seed)
    write_replay(rec, out, every=args.every, title=f"{label} on {core.config.scenario}:")
    print(f"wrote {out}: {label}, coverage {100 * rec.metrics['coverage']:.1f}% in "
          f"{len(rec.paths) - 1} steps")
    return 0


def _episode_output(args: argparse.Namespace, suffixes: tuple[str, ...]) -> Path:
    """``--out`` and ``--every`` of render/replay, checked before anything runs."""
    out = Path(args.out)
    if out.suffix.lower() not in suffixes:
        raise ConfigError(f"out={str(out)!r} is invalid: allowed a path ending in "
                          f"{' or '.join(suffixes)}")
    if args.every < 1:
        raise ConfigError(f"every={args.every} is invalid: allowed an integer >= 1")
    return out


def _episode_team(args: argparse.Namespace, checkpoint: str | None, policy: str):
    """(ScanCore, team, label): a checkpoint's team, else a scripted greedy/random team."""
    if checkpoint:
        return _checkpoint_team(args)
    from rl_scan.cli.env_args import env_config_from_args
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.heuristics import GreedyTeam, RandomTeam

    core = ScanCore(env_config_from_args(args))
    team = GreedyTeam(core) if policy == "greedy" else RandomTeam(core, seed=args.seed)
    return core, team, f"{policy} team"


def _checkpoint_team(args: argparse.Namespace):
    """ScanCore on the run's env config (flags override it) and the checkpoint's team."""
    from rl_scan.algorithms.rollout import (
        PolicyTeam,
        load_actors,
        resolve_checkpoint,
        run_env_config,
    )
    from rl_scan.cli.env_args import env_mapping_from_args
    from rl_scan.config import deep_merge
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.sim.env_config import make_env_config

    target = getattr(args, "checkpoint", None) or args.run
    if getattr(args, "best", False):
        from rl_scan.algorithms.rollout import best_checkpoint

        ckpt, args.best_info = best_checkpoint(target)
        args.best_info["checkpoint"] = str(ckpt)
    else:
        ckpt = resolve_checkpoint(target)
    config = make_env_config(deep_merge(run_env_config(ckpt), env_mapping_from_args(args)))
    core = ScanCore(config)
    import torch

    torch.manual_seed(getattr(args, "seed", 0))  # sampled actions are reproducible
    team = PolicyTeam(load_actors(ckpt), explore=not getattr(args, "deterministic", False))
    return core, team, f"checkpoint {ckpt}"


def evaluate_cmd(args: argparse.Namespace) -> int:
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    from rl_scan import metrics as M
    from rl_scan.envs.episode import run_episode
    from rl_scan.envs.heuristics import GreedyTeam

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
        _write_json(args.json, {"checkpoint": label, "seed": args.seed,
                                "deterministic": args.deterministic, "episodes": runs,
                                "summary": summary})
    if args.best:
        _record_best_eval(core, args, runs)
    return 0


def _record_best_eval(core, args: argparse.Namespace, runs: list[dict]) -> None:
    """Write BEST_EVAL_FILE into the checkpoint's run folder (for the report)."""
    ckpt = Path(args.best_info["checkpoint"])
    folder = run_dir_of(ckpt)
    if folder is None:
        print(f"note: {ckpt} belongs to no run folder; nothing recorded for the report")
        return
    out = folder / BEST_EVAL_FILE
    _write_json(str(out), {**args.best_info, "scenario": core.scenario_name, "episodes": len(runs),
                           "seed": args.seed, "deterministic": args.deterministic,
                           "coverage": [r["coverage"] for r in runs],
                           "success": [r["success"] for r in runs]})
    print(f"best checkpoint (iteration {args.best_info['training_iteration']}, training-time "
          f"eval {args.best_info['eval_coverage']:.3f}) recorded in {out}")


PRESET_FLAGS = (("num_env_runners", "num_env_runners"),
                ("num_envs_per_env_runner", "envs_per_runner"), ("learner_cpus", "learner_cpus"),
                ("overlap_sampling", "overlap_sampling"),
                ("total_env_steps", "total_env_steps"), ("sampler", "sampler"),
                ("custom_resources", "custom_resources"),
                ("evaluation_episodes", "evaluation_episodes"),
                ("evaluation_interval", "evaluation_interval"))
"""(preset field, command-line dest) of the flags that override a training preset."""


def preset_overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The preset fields this command's flags set (a flag left out keeps the preset's)."""
    return {field: getattr(args, dest) for field, dest in PRESET_FLAGS
            if getattr(args, dest, None) is not None}


def train_cmd(args: argparse.Namespace) -> int:
    from rl_scan.cli.env_args import env_mapping_from_args, parse_set
    from rl_scan.tuning.driver import make_run_spec
    from rl_scan.tuning.launch import train_spec

    overrides = preset_overrides_from_args(args)
    meta = parse_set(getattr(args, "meta", []), "--meta", "outer=reptile")
    spec = make_run_spec(args.algo, env_mapping_from_args(args), args.preset, seed=args.seed,
                         preset_overrides=overrides, init_from=getattr(args, "init_from", None),
                         settings_overrides=meta or None)
    run_dir = train_spec(spec, results_dir=args.results, name=args.name, address=args.address,
                         resume=args.resume)
    print(f"done: {run_dir}")
    return 0


def adapt_cmd(args: argparse.Namespace) -> int:
    args.algo, args.init_from = "poca", args.checkpoint
    if args.budget is not None:
        if args.budget < 1:
            raise ConfigError(f"budget={args.budget} is invalid: allowed >= 1 env steps")
        args.total_env_steps = args.budget
    return train_cmd(args)


def experiment_cmd(args: argparse.Namespace) -> int:
    from rl_scan.cli.env_args import parse_set
    from rl_scan.tuning.meta_mrss import Overrides, parse_tests, run_protocol

    budgets = {k: v for k, v in (("pretrain_steps", args.pretrain_steps),
                                 ("adapt_steps", args.adapt_steps)) if v is not None}
    overrides = Overrides(budgets=budgets, runs=preset_overrides_from_args(args) or {},
                          meta=parse_set(args.meta, "--meta", "relabel_query=true") or {})
    run_protocol(args.results, args.name, preset=args.preset,
                 methods=[m.strip() for m in args.methods.split(",") if m.strip()],
                 tests=parse_tests(args.tests), seeds=args.seeds, first_seed=args.seed,
                 overrides=overrides,
                 jobs=args.jobs, address=args.address)
    return 0


def hetero_map_cmd(args: argparse.Namespace) -> int:
    from rl_scan.tuning.hetero import hetero_map

    folder = hetero_map(args.results, args.name, scenes=args.scenes, resume=args.resume)
    print(f"done: {folder}  (optuna-dashboard sqlite:///{folder / OPTUNA_DB})")
    return 0


def ablate_cmd(args: argparse.Namespace) -> int:
    from rl_scan.cli.env_args import env_mapping_from_args
    from rl_scan.tuning.ablate import ablate

    overrides = preset_overrides_from_args(args)
    folder = ablate(args.study, args.preset, seeds=args.seeds, trials=args.trials,
                    results_dir=args.results, name=args.name, address=args.address,
                    resume=args.resume, env_config=env_mapping_from_args(args),
                    preset_overrides=overrides, conditions=args.conditions,
                    first_seed=args.seed)
    print(f"done: {folder}  (optuna-dashboard sqlite:///{folder / OPTUNA_DB})")
    return 0


def report_cmd(args: argparse.Namespace) -> int:
    from rl_scan.reports.build import build_report

    out = build_report(args.results_dir, args.out, reference=not args.no_reference,
                       compare=args.compare, add=args.add)
    print(f"wrote {out / 'report.md'}, {out / 'report.html'}, {out / 'marl_eval.json'}")
    return 0
