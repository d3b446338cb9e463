"""``rl-scan bench env``: simulator speed, adapter speed and scripted-team coverage.

All figures come from one run on one pinned core, so their ratios are meaningful even on
a noisy machine; the load average at the start is printed beside them. Targets (issue 3):
core >= 15,000 env steps/s; RLlib and PettingZoo adapters >= 5,000 env steps/s; greedy
team >= 95 % coverage on the ablation scene and >= 80 % mean on the five test scenes.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import resource
import time
from typing import Any

import numpy as np

from rl_scan import metrics as M
from rl_scan.envs.core import ScanCore
from rl_scan.envs.episode import run_episode
from rl_scan.envs.heuristics import GreedyTeam, RandomTeam
from rl_scan.envs.sim.env_config import EnvConfig
from rl_scan.envs.sim.raycast import cast_rays
from rl_scan.envs.sim.robots import ACTION_WIDTH
from rl_scan.envs.sim.scenarios import N_TEST

RAYCAST_LIMIT = 26e6  # rays/s/core of a plain numba DDA here (docs/library-facts.md)
TARGETS = {"core": 15_000, "rllib": 5_000, "pettingzoo": 5_000}


def _timed_loop(step, reset, seconds: float, episode_len: int) -> float:
    """Env steps per second of ``step(k)`` over ``seconds``, resetting every episode."""
    reset()
    n, t0 = 0, time.perf_counter()
    while True:
        for _ in range(200):
            step(n)
            n += 1
            if n % episode_len == 0:
                reset()
        elapsed = time.perf_counter() - t0
        if elapsed >= seconds:
            return n / elapsed


def bench_core(config: EnvConfig, seconds: float) -> dict[str, float]:
    """World.step with random actions, and the bare DDA kernel on the same kind of rays."""
    core = ScanCore(config)
    world = core.world
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (1000, world.n_robots, ACTION_WIDTH))
    core.reset(seed=0)
    world.step(actions[0])  # compile
    steps = _timed_loop(lambda k: world.step(actions[k % 1000]), lambda: world.reset(rng),
                        seconds, config.max_steps)
    # Rays of real poses: record the fans of 64 random states, then cast them in one batch.
    origins, dirs, ranges = [], [], []
    world.reset(rng)
    for k in range(64):
        world.step(actions[k])
        for i in range(world.n_robots):
            kind = world.kind[i]
            local = world.ray_dirs[kind, :world.n_rays[kind]]
            cp, sp = np.cos(world.pitch[i]), np.sin(world.pitch[i])
            cy, sy = np.cos(world.yaw[i]), np.sin(world.yaw[i])
            bx, bz = local[:, 0] * cp - local[:, 2] * sp, local[:, 0] * sp + local[:, 2] * cp
            d = np.stack([bx * cy - local[:, 1] * sy, bx * sy + local[:, 1] * cy, bz], axis=1)
            dirs.append(d)
            origins.append(np.repeat(world.pos[i][None], len(d), axis=0))
            ranges.append(np.full(len(d), world.sensor_range[kind]))
    o, d, r = np.concatenate(origins), np.concatenate(dirs), np.concatenate(ranges)
    out_t, out_c, out_f = np.empty(len(o)), np.empty(len(o), np.int64), np.empty(len(o), np.int64)
    args = (world.occ, world.shape_arr, world.grid.cell_size, o, d, r, out_t, out_c, out_f)
    cast_rays(*args)
    calls, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < max(0.5, seconds / 3):
        cast_rays(*args)
        calls += 1
    rays_per_s = calls * len(o) / (time.perf_counter() - t0)
    rays_per_step = int(world.n_rays[world.kind].sum())
    return {"core_steps_per_s": steps, "kernel_rays_per_s": rays_per_s,
            "rays_per_step": rays_per_step, "core_rays_per_s": steps * rays_per_step}


def bench_adapter(env, seconds: float, spaces: dict) -> float:
    """Env steps/s of an adapter's step() with pre-sampled actions (sampling not timed)."""
    rng = np.random.default_rng(0)
    acts = [{a: rng.uniform(-1, 1, sp.shape).astype(np.float32) for a, sp in spaces.items()}
            for _ in range(500)]
    state = {"seed": 0}

    def reset():
        state["seed"] += 1
        env.reset(seed=state["seed"])

    def step(k):
        env.step(acts[k % 500])
        if not env.agents:  # both adapters empty it when the episode ends
            reset()

    return _timed_loop(step, reset, seconds, 10**9)


def bench_teams(config: EnvConfig, seeds: int) -> dict[str, Any]:
    """Coverage of the greedy and random teams on the ablation and the test scenarios."""
    out: dict[str, Any] = {}
    for scenario in ["ablation"] + [f"test:{i}" for i in range(N_TEST)]:
        core = ScanCore(dataclasses.replace(config, scenario=scenario))
        for name, make in (("greedy", GreedyTeam), ("random", RandomTeam)):
            runs = [run_episode(core, make(core), seed=s) for s in range(seeds)]
            out[(scenario, name)] = {k: float(np.nanmean([r[k] for r in runs]))
                                     if not all(np.isnan(r[k]) for r in runs) else float("nan")
                                     for k in runs[0]}
    return out


def run_bench_env(config: EnvConfig, seconds: float = 3.0, seeds: int = 3,
                  pin_core: bool = True, console=None) -> dict[str, Any]:
    """Run every env benchmark and print a table; returns the figures as a dict."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    if pin_core and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    load = os.getloadavg()
    console.print(f"[bold]rl-scan bench env[/] scenario={config.scenario} team="
                  f"{config.team.wheeled}w+{config.team.quad}q  python {platform.python_version()}"
                  f"  cpu pinned={pin_core}  load avg {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    t0 = time.perf_counter()
    res: dict[str, Any] = {"load_avg_1m": load[0], "scenario": config.scenario}
    res.update(bench_core(config, seconds))
    console.print(f"core simulator: {res['core_steps_per_s']:,.0f} env steps/s", highlight=False)

    from rl_scan.envs.parallel_env import ScanParallelEnv
    from rl_scan.envs.rllib_env import ScanMultiAgentEnv

    console.print("measuring the RLlib and PettingZoo adapters ...")
    rl = ScanMultiAgentEnv(_config_dict(config))
    res["rllib_steps_per_s"] = bench_adapter(rl, seconds, rl.action_spaces)
    pz = ScanParallelEnv(_config_dict(config))
    res["pettingzoo_steps_per_s"] = bench_adapter(
        pz, seconds, {a: pz.action_space(a) for a in pz.possible_agents})
    console.print(f"playing greedy and random teams, {seeds} episode(s) per scene ...")
    teams = bench_teams(config, seeds)
    res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    res["wall_s"] = time.perf_counter() - t0

    speed = Table(title="Speed (one core, same run)")
    for col in ("measure", "value", "target", "ratio"):
        speed.add_column(col, justify="right" if col != "measure" else "left")
    rows = [("core simulator env steps/s", res["core_steps_per_s"], TARGETS["core"]),
            ("RLlib MultiAgentEnv env steps/s", res["rllib_steps_per_s"], TARGETS["rllib"]),
            ("PettingZoo ParallelEnv env steps/s", res["pettingzoo_steps_per_s"],
             TARGETS["pettingzoo"])]
    for name, value, target in rows:
        speed.add_row(name, f"{value:,.0f}", f">= {target:,}", f"{value / target:.2f}x")
    speed.add_row("raycast kernel rays/s (DDA alone)", f"{res['kernel_rays_per_s'] / 1e6:.1f} M",
                  f"limit {RAYCAST_LIMIT / 1e6:.0f} M",
                  f"{res['kernel_rays_per_s'] / RAYCAST_LIMIT:.2f}x")
    speed.add_row(f"rays/s inside env steps ({res['rays_per_step']} rays/step)",
                  f"{res['core_rays_per_s'] / 1e6:.1f} M", f"limit {RAYCAST_LIMIT / 1e6:.0f} M",
                  f"{res['core_rays_per_s'] / RAYCAST_LIMIT:.2f}x")
    speed.add_row("peak memory (RSS)", f"{res['peak_rss_mb']:.0f} MB", "", "")
    console.print(speed)

    cov = Table(title=f"Scripted teams: coverage at max_steps={config.max_steps} "
                      f"(mean of {seeds} seeds)")
    for col in ("scenario", "cells", "greedy coverage", "greedy steps to 95%",
                "greedy collisions", "random coverage"):
        cov.add_column(col, justify="right" if col != "scenario" else "left")
    for scenario in ["ablation"] + [f"test:{i}" for i in range(N_TEST)]:
        g, r = teams[(scenario, "greedy")], teams[(scenario, "random")]
        s95 = g[M.STEPS_TO[0.95]]
        cov.add_row(scenario, f"{g[M.CELLS_TOTAL]:.0f}", f"{100 * g[M.COVERAGE]:.1f}%",
                    "-" if np.isnan(s95) else f"{s95:.0f}", f"{g[M.COLLISIONS]:.1f}",
                    f"{100 * r[M.COVERAGE]:.1f}%")
    test_g = np.mean([teams[(f"test:{i}", "greedy")][M.COVERAGE] for i in range(N_TEST)])
    test_r = np.mean([teams[(f"test:{i}", "random")][M.COVERAGE] for i in range(N_TEST)])
    cov.add_row("test mean", "", f"{100 * test_g:.1f}%", "", "", f"{100 * test_r:.1f}%")
    console.print(cov)
    res["greedy_ablation_coverage"] = teams[("ablation", "greedy")][M.COVERAGE]
    res["random_ablation_coverage"] = teams[("ablation", "random")][M.COVERAGE]
    res["greedy_test_coverage"], res["random_test_coverage"] = float(test_g), float(test_r)
    res["teams"] = {f"{s}/{n}": v for (s, n), v in teams.items()}
    checks = [("core >= 15k steps/s", res["core_steps_per_s"] >= TARGETS["core"]),
              ("adapters >= 5k steps/s", min(res["rllib_steps_per_s"],
                                              res["pettingzoo_steps_per_s"]) >= 5_000),
              ("greedy >= 95% on ablation", res["greedy_ablation_coverage"] >= 0.95),
              ("greedy >= 80% mean on test", test_g >= 0.80)]
    console.print("  ".join(f"{'[green]PASS' if ok else '[red]FAIL'}[/] {name}"
                            for name, ok in checks))
    console.print(f"wall time {res['wall_s']:.1f} s")
    res["checks"] = {name: bool(ok) for name, ok in checks}
    return res


def _config_dict(config: EnvConfig) -> dict[str, Any]:
    from rl_scan.config import to_dict

    return to_dict(config)
