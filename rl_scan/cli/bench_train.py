"""``rl-scan bench train``: where a training iteration's time goes, measured in one run.

For stock RLlib PPO (RLlib's ``MultiAgentEnvRunner``), PPO on the fast sampler and POCA on
the fast sampler, at the same batch sizes and torch threads, it measures separately:

  env only       the RLlib adapter stepped with random actions (no RLlib loop);
  sampling only  ``env_runner.sample(num_timesteps=batch)`` with the module acting;
  learner only   ``learner_group.update`` on pre-sampled episodes (connectors, epochs,
                 minibatches, optimizer): the learner's limit;
  end to end     ``Algorithm.train()`` (sampling, learning, weight sync, metrics);

plus peak RSS, the learner's FLOPs per env step (counted by ``torch.utils.flop_counter``
over one update, so it is exact for the network as built) and its achieved GFLOP/s beside a
torch matmul roof measured in the same run with the same threads. Then the sampling-only
speed of the fast sampler with 1 and 2 remote env runners. Ratios are printed at the end;
compare figures only within one run (the machine's speed varies from day to day).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from rl_scan import results as R
from rl_scan.algorithms.registry import get_algorithm
from rl_scan.envs.sim.env_config import EnvConfig

REFERENCE = ("ppo", "rllib")
CONFIGS = (REFERENCE, ("ppo", "fast"), ("poca", "fast"))
ROOF_SHAPE = (4096, 1296, 256)  # a minibatch through the first ray-encoder layer


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


def matmul_roof_gflops(seconds: float = 1.0) -> float:
    """float32 GFLOP/s of torch's matmul on this machine at the current thread count."""
    import torch

    m, k, n = ROOF_SHAPE
    a, b = torch.randn(m, k), torch.randn(k, n)
    a @ b  # warm up
    reps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a @ b
        reps += 1
    return 2 * m * k * n * reps / (time.perf_counter() - t0) / 1e9


def adapter_steps_per_s(env_config: EnvConfig, seconds: float = 2.0) -> float:
    """The RLlib adapter alone: env steps/s with random actions, one env."""
    import numpy as np

    from rl_scan.config import to_dict
    from rl_scan.envs.rllib_env import ScanMultiAgentEnv

    env = ScanMultiAgentEnv(to_dict(env_config))
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        actions = {a: rng.uniform(-1, 1, s.shape).astype(np.float32)
                   for a, s in env.action_spaces.items()}
        _, _, terms, truncs, _ = env.step(actions)
        steps += 1
        if terms["__all__"] or truncs["__all__"]:
            env.reset()
    return steps / (time.perf_counter() - t0)


def _rate(steps: int, seconds: float) -> float:
    return steps / seconds if seconds > 0 else float("nan")


def measure(algo: str, sampler: str, env_config: EnvConfig, *, batch: int, minibatch: int,
            epochs: int, envs_per_runner: int, iterations: int) -> dict[str, float]:
    """Sampling-only, learner-only and end-to-end env steps/s of one configuration."""
    from torch.utils.flop_counter import FlopCounterMode

    config = get_algorithm(algo).load_builder()(
        env_config, train_batch_size=batch, minibatch_size=minibatch, num_epochs=epochs,
        num_envs_per_env_runner=envs_per_runner, sampler=sampler)
    algorithm = config.build_algo()
    try:
        algorithm.train()  # warm-up: compile, allocate, fill windows
        runner, learners = algorithm.env_runner, algorithm.learner_group
        t0 = time.perf_counter()
        batches = [runner.sample(num_timesteps=batch) for _ in range(iterations)]
        sampling_s = time.perf_counter() - t0
        steps = sum(sum(len(e) for e in episodes) for episodes in batches)
        t0 = time.perf_counter()
        for episodes in batches:
            learners.update(episodes=episodes, num_epochs=epochs, minibatch_size=minibatch,
                            shuffle_batch_per_epoch=True)
        learner_s = time.perf_counter() - t0
        with FlopCounterMode(display=False) as flops:
            learners.update(episodes=batches[0], num_epochs=epochs, minibatch_size=minibatch,
                            shuffle_batch_per_epoch=True)
        flops_per_step = flops.get_total_flops() / sum(len(e) for e in batches[0])
        start = algorithm.train()[R.ENV_STEPS]
        t0 = time.perf_counter()
        for _ in range(iterations):
            result = algorithm.train()
        e2e_s = time.perf_counter() - t0
        e2e_steps = result[R.ENV_STEPS] - start
        learner_rate = _rate(steps, learner_s)
        return {"sampling_env_steps_per_s": _rate(steps, sampling_s),
                "learner_env_steps_per_s": learner_rate,
                "env_steps_per_s": _rate(e2e_steps, e2e_s),
                "s_per_iter": e2e_s / iterations,
                "learner_gflop_per_env_step": flops_per_step / 1e9,
                "learner_gflops": flops_per_step * learner_rate / 1e9,
                "peak_rss_mb": ray_tree_peak_rss_mb()}
    finally:
        algorithm.stop()


def remote_sampling(runners: int, env_config: EnvConfig, *, batch: int,
                    envs_per_runner: int, iterations: int) -> float:
    """Fast-sampler env steps/s of ``runners`` remote env runners sampling at once."""
    config = get_algorithm("ppo").load_builder()(
        env_config, train_batch_size=batch, minibatch_size=batch, num_epochs=1,
        num_env_runners=runners, num_envs_per_env_runner=envs_per_runner, sampler="fast")
    algorithm = config.build_algo()
    per_runner = -(-batch // runners)
    try:
        def sample(runner):
            return sum(len(e) for e in runner.sample(num_timesteps=per_runner))

        algorithm.env_runner_group.foreach_env_runner(sample, local_env_runner=False)
        t0, steps = time.perf_counter(), 0
        for _ in range(iterations):
            steps += sum(algorithm.env_runner_group.foreach_env_runner(
                sample, local_env_runner=False))
        return _rate(steps, time.perf_counter() - t0)
    finally:
        algorithm.stop()


def run_bench_train(env_config: EnvConfig, *, iterations: int = 3, batch: int = 4000,
                    minibatch: int = 1024, epochs: int = 3, envs_per_runner: int = 4,
                    threads: int = 1, console=None) -> dict[str, Any]:
    """Measure every configuration of ``CONFIGS`` and the runner scaling; print a table."""
    import ray
    import torch
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    torch.set_num_threads(threads)
    if not ray.is_initialized():
        ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False)
    load = os.getloadavg()[0]
    console.print(f"[bold]rl-scan bench train[/] batch {batch} env steps, minibatch "
                  f"{minibatch}, {epochs} epochs, {envs_per_runner} envs per runner, "
                  f"{iterations} timed iterations, torch threads {torch.get_num_threads()}; "
                  f"load avg {load:.2f}")
    roof = matmul_roof_gflops()
    env_only = adapter_steps_per_s(env_config)
    size = dict(batch=batch, minibatch=minibatch, epochs=epochs,
                envs_per_runner=envs_per_runner, iterations=iterations)
    runs: dict[str, dict[str, float]] = {}
    for algo, sampler in CONFIGS:
        console.print(f"measuring {algo} on the {sampler} sampler ...")
        runs[f"{algo}/{sampler}"] = measure(algo, sampler, env_config, **size)
    scaling = {n: remote_sampling(n, env_config, batch=batch, envs_per_runner=envs_per_runner,
                                  iterations=iterations) for n in (1, 2)}
    table = Table(title=f"Training throughput, env steps/s (env only: {env_only:,.0f}; "
                        f"matmul roof {roof:.1f} GFLOP/s)")
    for col in ("configuration", "sampling only", "learner only", "end to end", "s/iter",
                "GFLOP/env step", "learner GFLOP/s", "peak RSS"):
        table.add_column(col, justify="left" if col == "configuration" else "right")
    for label, r in runs.items():
        table.add_row(label, f"{r['sampling_env_steps_per_s']:,.0f}",
                      f"{r['learner_env_steps_per_s']:,.0f}", f"{r['env_steps_per_s']:,.0f}",
                      f"{r['s_per_iter']:.2f}", f"{r['learner_gflop_per_env_step']:.3f}",
                      f"{r['learner_gflops']:.1f}", f"{r['peak_rss_mb']:,.0f} MB")
    console.print(table)
    ref = runs["/".join(REFERENCE)]
    ratios = {
        "ppo/fast / ppo/rllib, end to end": runs["ppo/fast"]["env_steps_per_s"]
        / ref["env_steps_per_s"],
        "poca/fast / ppo/rllib, end to end": runs["poca/fast"]["env_steps_per_s"]
        / ref["env_steps_per_s"],
        "ppo/fast / ppo/rllib, sampling only": runs["ppo/fast"]["sampling_env_steps_per_s"]
        / ref["sampling_env_steps_per_s"],
        "2 / 1 remote fast runners, sampling only": scaling[2] / scaling[1]}
    for label in ("ppo/fast", "poca/fast"):
        r = runs[label]
        ratios[f"{label} end to end / learner only"] = (r["env_steps_per_s"]
                                                        / r["learner_env_steps_per_s"])
        ratios[f"{label} learner / matmul roof"] = r["learner_gflops"] / roof
    for k, v in ratios.items():
        console.print(f"  {k}: {v:.2f}x")
    return {"runs": runs, "ratios": ratios, "env_only_env_steps_per_s": env_only,
            "matmul_roof_gflops": roof, "remote_sampling_env_steps_per_s": scaling,
            "torch_threads": torch.get_num_threads(), "load_avg_1m": load}
