"""The fast sampling path: an RLlib EnvRunner that samples every world of a runner in
batches (``sampler="fast"``, the default; ``"rllib"`` is RLlib's own runner)."""

from rl_scan.algorithms.fast_runner.runner import FastEnvRunner
from rl_scan.algorithms.fast_runner.support import check_fast_sampler

__all__ = ["FastEnvRunner", "check_fast_sampler"]
