"""``rl-scan bench train``: end-to-end training throughput, measured in one run.

For each configuration it builds the algorithm (local Ray, 2 CPUs by default), runs one
warm-up iteration, then times ``iterations`` calls of ``train()`` and reports env steps
per second (sampling + learning), seconds per iteration and the summed peak RSS of the
Ray process tree. Targets (issue 4): POCA >= 0.8x PPO on the same env and batch sizes;
2 env runners >= 1.5x one env runner.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from rl_scan import results as R
from rl_scan.algorithms.registry import get_algorithm
from rl_scan.envs.sim.env_config import EnvConfig


def ray_tree_peak_rss_mb() -> float:
    """Sum of peak RSS (VmHWM) of this process and every Ray process on the machine."""
    total_kb = 0
    for status in Path("/proc").glob("[0-9]*/status"):
        try:
            text = status.read_text()
            cmd = (status.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(status.parent.name) != os.getpid() and b"ray" not in cmd:
            continue
        for line in text.splitlines():
            if line.startswith("VmHWM:"):
                total_kb += int(line.split()[1])
    return total_kb / 1024


def measure(algo: str, env_config: EnvConfig, *, train_batch_size: int,
            minibatch_size: int, num_epochs: int, num_env_runners: int,
            num_envs_per_env_runner: int, iterations: int) -> dict[str, float]:
    """Env steps/s of ``iterations`` train() calls after one warm-up iteration."""
    config = get_algorithm(algo).load_builder()(env_config, train_batch_size=train_batch_size,
                     minibatch_size=minibatch_size, num_epochs=num_epochs,
                     num_env_runners=num_env_runners,
                     num_envs_per_env_runner=num_envs_per_env_runner)
    algorithm = config.build_algo()
    try:
        algorithm.train()
        start_steps = None
        sampling_s = 0.0
        t0 = time.perf_counter()
        for _ in range(iterations):
            result = algorithm.train()
            sampling_s += result["timers"]["env_runner_sampling_timer"]
            if start_steps is None:
                start_steps = result[R.ENV_STEPS] - train_batch_size
        elapsed = time.perf_counter() - t0
        steps = result[R.ENV_STEPS] - start_steps
        return {"env_steps_per_s": steps / elapsed, "s_per_iter": elapsed / iterations,
                # sampling alone (RLlib's smoothed timer): what more env runners speed up
                "sampling_env_steps_per_s": steps / sampling_s,
                "peak_rss_mb": ray_tree_peak_rss_mb()}
    finally:
        algorithm.stop()


def run_bench_train(env_config: EnvConfig, algos: list[str], *, iterations: int = 3,
                    train_batch_size: int = 2000, minibatch_size: int = 512,
                    num_epochs: int = 3, envs_per_runner: int = 4, console=None) -> dict:
    """Measure each algorithm at 0 runners, and the first one at 1 and 2 runners."""
    import ray
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    if not ray.is_initialized():
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    load = os.getloadavg()
    console.print(f"[bold]rl-scan bench train[/] batch {train_batch_size} env steps, "
                  f"minibatch {minibatch_size}, {num_epochs} epochs, {iterations} timed "
                  f"iterations; load avg {load[0]:.2f}")
    common = dict(train_batch_size=train_batch_size, minibatch_size=minibatch_size,
                  num_epochs=num_epochs, num_envs_per_env_runner=envs_per_runner,
                  iterations=iterations)
    runs: dict[str, dict[str, float]] = {}
    plan = [(a, 0) for a in algos] + [(algos[0], 1), (algos[0], 2)]
    for algo, runners in plan:
        label = f"{algo}, {runners} env runner(s) x {envs_per_runner} envs"
        console.print(f"measuring {label} ...")
        runs[label] = measure(algo, env_config, num_env_runners=runners, **common)
    table = Table(title="Training throughput (same run)")
    for col in ("configuration", "env steps/s", "s/iteration", "sampling-only steps/s",
                "peak RSS, Ray tree"):
        table.add_column(col, justify="left" if col == "configuration" else "right")
    for label, r in runs.items():
        table.add_row(label, f"{r['env_steps_per_s']:,.0f}", f"{r['s_per_iter']:.2f}",
                      f"{r['sampling_env_steps_per_s']:,.0f}", f"{r['peak_rss_mb']:,.0f} MB")
    console.print(table)
    base = runs[f"{algos[0]}, 0 env runner(s) x {envs_per_runner} envs"]["env_steps_per_s"]
    ratios = {}
    for algo in algos[1:]:
        ratios[f"{algo} / {algos[0]}"] = (
            runs[f"{algo}, 0 env runner(s) x {envs_per_runner} envs"]["env_steps_per_s"] / base)
    one = runs[f"{algos[0]}, 1 env runner(s) x {envs_per_runner} envs"]["env_steps_per_s"]
    two = runs[f"{algos[0]}, 2 env runner(s) x {envs_per_runner} envs"]["env_steps_per_s"]
    ratios["2 runners / 1 runner"] = two / one
    sampling = {n: runs[f"{algos[0]}, {n} env runner(s) x {envs_per_runner} envs"]
                ["sampling_env_steps_per_s"] for n in (1, 2)}
    # the learner update is serial on the driver, so end to end it is Amdahl-bound
    ratios["2 runners / 1 runner, sampling only"] = sampling[2] / sampling[1]
    console.print("  ".join(f"{k}: {v:.2f}x" for k, v in ratios.items()))
    return {"runs": runs, "ratios": ratios, "load_avg_1m": load[0]}
