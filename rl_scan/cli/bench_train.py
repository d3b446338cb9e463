"""``rl-scan bench train``: where a training iteration's time goes, measured in one run.

For stock RLlib PPO (RLlib's ``MultiAgentEnvRunner``), PPO and POCA on the fast sampler, and
both again with sampling overlapped with learning (one remote runner,
``rl_scan.algorithms.overlap``), at the same batch sizes and torch threads, it measures
separately:

  env only       the RLlib adapter stepped with random actions (no RLlib loop);
  sampling only  ``env_runner.sample(num_timesteps=batch)`` with the module acting;
  learner only   ``learner_group.update`` on pre-sampled episodes (connectors, epochs,
                 minibatches, optimizer): the learner's limit;
  end to end     ``Algorithm.train()`` (sampling, learning, weight sync, metrics);

plus memory (the largest process's peak RSS and the PSS of all of the run's processes), the
learner's FLOPs per env step (counted by ``torch.utils.flop_counter``
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

REFERENCE = "ppo/rllib"
CONFIGS = {  # label: (algorithm, sampler, overlap sampling with one remote runner)
    REFERENCE: ("ppo", "rllib", False), "ppo/fast": ("ppo", "fast", False),
    "poca/fast": ("poca", "fast", False), "ppo/fast+overlap": ("ppo", "fast", True),
    "poca/fast+overlap": ("poca", "fast", True)}
ROOF_SHAPE = (4096, 1296, 256)  # a minibatch through the first ray-encoder layer


def _descendants(root: int) -> list[int]:
    """``root`` and every process below it (Ray's raylet, GCS and workers of our session)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(stat.parent.name))
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo += children.get(pid, [])
    return out


def reset_peak_rss() -> None:
    """Start this process's peak RSS afresh (Linux: "5" > /proc/self/clear_refs), so each
    configuration's figure is its own; the runners' processes are new per configuration."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def process_tree_memory_mb() -> dict[str, float]:
    """Memory of this process and its descendants: the largest single peak RSS (VmHWM),
    and the proportional set size (PSS: shared libraries split between the processes that
    map them, so torch's ~0.3 GB is counted once) summed over the tree now."""
    peak_kb, pss_kb = 0, 0
    for pid in _descendants(os.getpid()):
        try:
            status = Path(f"/proc/{pid}/status").read_text()
            rollup = Path(f"/proc/{pid}/smaps_rollup").read_text()
        except OSError:
            continue
        for line in status.splitlines():
            if line.startswith("VmHWM:"):
                peak_kb = max(peak_kb, int(line.split()[1]))
        for line in rollup.splitlines():
            if line.startswith("Pss:"):
                pss_kb += int(line.split()[1])
    return {"largest_process_peak_rss_mb": peak_kb / 1024, "tree_pss_mb": pss_kb / 1024}


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


def _sample_remote(runner, num_timesteps: int) -> list:
    return runner.sample(num_timesteps=num_timesteps)


def _drain_metrics(runner) -> None:
    runner.get_metrics()


def measure(algo: str, sampler: str, env_config: EnvConfig, *, batch: int, minibatch: int,
            epochs: int, envs_per_runner: int, iterations: int,
            overlap: bool = False) -> dict[str, float]:
    """Sampling-only, learner-only and end-to-end env steps/s of one configuration.

    With ``overlap`` one remote runner samples (sampling-only then includes shipping the
    episodes to this process, as training receives them)."""
    from torch.utils.flop_counter import FlopCounterMode

    reset_peak_rss()
    config = get_algorithm(algo).load_builder()(
        env_config, train_batch_size=batch, minibatch_size=minibatch, num_epochs=epochs,
        num_envs_per_env_runner=envs_per_runner, sampler=sampler,
        num_env_runners=int(overlap), overlap_sampling=overlap)
    algorithm = config.build_algo()
    try:
        algorithm.train()  # warm-up: compile, allocate, fill windows
        runners, learners = algorithm.env_runner_group, algorithm.learner_group

        def sample():
            if not overlap:
                return algorithm.env_runner.sample(num_timesteps=batch)
            return runners.foreach_env_runner(_sample_remote, local_env_runner=False,
                                              kwargs={"num_timesteps": batch})[0]

        t0 = time.perf_counter()
        batches = [sample() for _ in range(iterations)]
        sampling_s = time.perf_counter() - t0
        # Drop the runners' counts of these steps: train() must count only its own.
        if overlap:
            runners.foreach_env_runner(_drain_metrics, local_env_runner=False)
        else:
            algorithm.env_runner.get_metrics()
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
                **process_tree_memory_mb()}
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
    for label, (algo, sampler, overlap) in CONFIGS.items():
        console.print(f"measuring {label} ...")
        runs[label] = measure(algo, sampler, env_config, overlap=overlap, **size)
    scaling = {n: remote_sampling(n, env_config, batch=batch, envs_per_runner=envs_per_runner,
                                  iterations=iterations) for n in (1, 2)}
    table = Table(title=f"Training throughput, env steps/s (env only: {env_only:,.0f}; "
                        f"matmul roof {roof:.1f} GFLOP/s)")
    table.add_column("configuration", no_wrap=True)
    for col in ("sampling only", "learner only", "end to end", "s/iter", "GFLOP/ step",
                "learner GFLOP/s", "peak RSS (largest process)", "PSS (all processes)"):
        table.add_column(col, justify="right")
    for label, r in runs.items():
        table.add_row(label, f"{r['sampling_env_steps_per_s']:,.0f}",
                      f"{r['learner_env_steps_per_s']:,.0f}", f"{r['env_steps_per_s']:,.0f}",
                      f"{r['s_per_iter']:.2f}", f"{r['learner_gflop_per_env_step']:.3f}",
                      f"{r['learner_gflops']:.1f}",
                      f"{r['largest_process_peak_rss_mb']:,.0f} MB",
                      f"{r['tree_pss_mb']:,.0f} MB")
    console.print(table)
    ref = runs[REFERENCE]
    ratios = {f"{label} / {REFERENCE}, end to end": r["env_steps_per_s"]
              / ref["env_steps_per_s"] for label, r in runs.items() if label != REFERENCE}
    ratios.update({
        f"ppo/fast / {REFERENCE}, sampling only": runs["ppo/fast"]["sampling_env_steps_per_s"]
        / ref["sampling_env_steps_per_s"],
        "2 / 1 remote fast runners, sampling only": scaling[2] / scaling[1]})
    for label in (k for k in runs if k != REFERENCE):
        r = runs[label]
        ratios[f"{label} end to end / learner only"] = (r["env_steps_per_s"]
                                                        / r["learner_env_steps_per_s"])
        ratios[f"{label} learner / matmul roof"] = r["learner_gflops"] / roof
    for k, v in ratios.items():
        console.print(f"  {k}: {v:.2f}x")
    return {"runs": runs, "ratios": ratios, "env_only_env_steps_per_s": env_only,
            "matmul_roof_gflops": roof, "remote_sampling_env_steps_per_s": scaling,
            "torch_threads": torch.get_num_threads(), "load_avg_1m": load}
