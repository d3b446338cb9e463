"""meta-MRSS (the paper's Algorithm 1): MAML over POCA as an RLlib algorithm.

Per meta-iteration: sample ``meta_tasks`` scenarios from the train set; per task, sample
``meta_episodes`` support episodes with the meta policy, adapt (``inner_steps`` inner
steps, first order with Adam by default), sample as many query episodes with the adapted
policy; then ``meta_epochs`` meta updates over the task batch (``learners.py``).

    config = meta_poca_config({"max_steps": 200}, tasks=4, episodes=2)
    algo = config.build_algo(); algo.train(); algo.save_to_path("ckpt")

Sampling runs on the local env runner (``num_env_runners=0``): tasks are set per env and
adapted weights are loaded between support and query sampling.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from ray.rllib.algorithms.algorithm_config import DifferentiableAlgorithmConfig, NotProvided
from ray.rllib.utils.annotations import override
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    ENV_RUNNER_SAMPLING_TIMER,
    LEARNER_RESULTS,
    LEARNER_UPDATE_TIMER,
    TIMERS,
)

from rl_scan.algorithms.callbacks import episode_summary
from rl_scan.algorithms.maml.learners import (
    MetaPOCALearner,
    MultiAgentDifferentiableLearnerConfig,
    POCADifferentiableLearner,
)
from rl_scan.algorithms.poca.modules import CRITIC_ID
from rl_scan.algorithms.poca.poca import POCA, POCAConfig, poca_config
from rl_scan.config import ConfigError, check_range
from rl_scan.envs.sim.env_config import EnvConfig
from rl_scan.envs.sim.scenarios import N_TRAIN
from rl_scan.results import META_AFTER, META_BEFORE


class MetaPOCAConfig(POCAConfig, DifferentiableAlgorithmConfig):
    """POCAConfig plus the meta-learning settings (paper: I=100, tau=10, K=20)."""

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or MetaPOCA)
        self.meta_tasks = 10
        self.meta_episodes = 20
        self.inner_steps = 1
        self.inner_lr = 3e-4
        self.meta_order = 1
        self.meta_epochs = 3
        self.task_pool = N_TRAIN
        # PopArt rescales the critic's output layer in place whenever its statistics move,
        # i.e. in every adaptation's connector pass: the meta-parameters would change
        # outside the meta-step. Off until the meta-learner owns the statistics.
        self.normalize_returns = False

    def meta(self, *, tasks: int = NotProvided, episodes: int = NotProvided,
             inner_steps: int = NotProvided, inner_lr: float = NotProvided,
             order: int = NotProvided, epochs: int = NotProvided,
             task_pool: int = NotProvided) -> MetaPOCAConfig:
        """Meta settings: ``tasks`` per meta-iteration (tau), support/query ``episodes`` per
        task (K), ``inner_steps`` and ``inner_lr`` of the adaptation, ``order`` 1 (first
        order, inner Adam) or 2 (second order, inner SGD), ``epochs``: meta steps per
        meta-iteration on its query episodes (the paper's 3), and ``task_pool``: tasks
        are drawn from ``train:0`` .. ``train:{task_pool - 1}``."""
        for name, value in (("meta_tasks", tasks), ("meta_episodes", episodes),
                            ("inner_steps", inner_steps), ("inner_lr", inner_lr),
                            ("meta_order", order), ("meta_epochs", epochs),
                            ("task_pool", task_pool)):
            if value is not NotProvided:
                setattr(self, name, value)
        self.sync_inner_learner_config()
        return self

    @override(POCAConfig)
    def get_default_learner_class(self):
        return MetaPOCALearner

    @override(POCAConfig)
    def validate(self) -> None:
        check_range("meta.tasks", self.meta_tasks, 1)
        check_range("meta.episodes", self.meta_episodes, 1)
        check_range("meta.inner_steps", self.inner_steps, 1)
        check_range("meta.inner_lr", self.inner_lr, 0.0, lo_open=True)
        check_range("meta.epochs", self.meta_epochs, 1, 100)
        check_range("meta.task_pool", self.task_pool, 1, N_TRAIN)
        check_range("meta.tasks", self.meta_tasks, 1, self.task_pool)  # distinct tasks
        if self.meta_order not in (1, 2):
            raise ConfigError(f"meta.order={self.meta_order!r}: allowed 1 (first order, "
                              "inner Adam) or 2 (second order, inner SGD)")
        if self.num_env_runners != 0:
            raise ConfigError(f"num_env_runners={self.num_env_runners}: MetaPOCA samples "
                              "its tasks on the local env runner; allowed: 0")
        if not isinstance(self.entropy_coeff, (int, float)):
            raise ConfigError("entropy_coeff: MetaPOCA needs a constant (no schedule)")
        if not self._is_frozen:
            self.sync_inner_learner_config()
        super().validate()

    def sync_inner_learner_config(self) -> None:
        """The inner (differentiable) learner's config, from the meta settings."""
        self.differentiable_learner_configs = [MultiAgentDifferentiableLearnerConfig(
            POCADifferentiableLearner, is_multi_agent=True, policies=set(self.policies),
            policy_mapping_fn=self.policy_mapping_fn, lr=self.inner_lr,
            num_epochs=self.inner_steps, minibatch_size=None, meta_order=self.meta_order)]


def set_task(env_runner, scenario: str) -> None:
    """Every env of a (local) env runner uses ``scenario`` from its next reset on."""
    for env in env_runner.env.unwrapped.envs:
        env.unwrapped.set_task(scenario)


def mean_coverage(episodes: list) -> float:
    values = [s["coverage"] for s in map(episode_summary, episodes) if s is not None]
    return float(np.mean(values)) if values else float("nan")


class MetaPOCA(POCA):
    """meta-MRSS: first- or second-order MAML over POCA (see the module doc)."""

    @classmethod
    @override(POCA)
    def get_default_config(cls) -> MetaPOCAConfig:
        return MetaPOCAConfig()

    def meta_tasks_of(self, iteration: int) -> list[str]:
        """The iteration's task scenarios: a function of (seed, iteration), so resumes
        draw the same tasks."""
        cfg = self.config
        rng = np.random.default_rng([cfg.seed or 0, iteration])
        ids = rng.choice(cfg.task_pool, size=cfg.meta_tasks, replace=False)
        return [f"train:{int(i)}" for i in ids]

    @override(POCA)
    def training_step(self) -> None:
        cfg = self.config
        runner = self.env_runner
        learner = self.learner_group._learner  # num_learners=0: the local learner
        actor_ids = [mid for mid in runner.module.keys() if mid != CRITIC_ID]
        meta_state = {mid: {k: v.clone() for k, v in runner.module[mid].state_dict().items()}
                      for mid in actor_ids}
        tasks, before, after = [], [], []
        for scenario in self.meta_tasks_of(self.iteration):
            set_task(runner, scenario)
            with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
                self._load_actors(runner, meta_state)
                support = runner.sample(num_episodes=cfg.meta_episodes)
            with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
                adapted = learner.adapt(support)
            with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
                self._load_actors(runner, learner.adapted_state(adapted))
                query = runner.sample(num_episodes=cfg.meta_episodes)
            tasks.append({"support": support, "query": query, "adapted": adapted})
            before.append(mean_coverage(support))
            after.append(mean_coverage(query))
        set_task(runner, cfg.env_config.get("scenario", "ablation"))
        self.metrics.aggregate([runner.get_metrics()], key=ENV_RUNNER_RESULTS)
        with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
            results = learner.meta_update(tasks)
        self.metrics.aggregate([results], key=LEARNER_RESULTS)
        self.env_runner_group.sync_weights(from_worker_or_learner_group=self.learner_group,
                                           policies=actor_ids, inference_only=True)
        # coverage with the meta policy (support) and after adaptation (query)
        self.metrics.log_value(META_BEFORE, float(np.mean(before)), window=1)
        self.metrics.log_value(META_AFTER, float(np.mean(after)), window=1)

    @staticmethod
    def _load_actors(runner, state: dict[str, dict[str, torch.Tensor]]) -> None:
        for mid, sd in state.items():
            runner.module[mid].load_state_dict(sd)


def meta_poca_config(env_config: EnvConfig | dict[str, Any], *, tasks: int = 10, episodes: int = 20,
                     inner_steps: int = 1, inner_lr: float = 3e-4, order: int = 1,
                     meta_epochs: int = 3, task_pool: int = N_TRAIN, train_batch_size: int = 1,
                     minibatch_size: int = 1, **poca_kwargs: Any) -> MetaPOCAConfig:
    """MetaPOCAConfig for the scanning env: POCA's settings plus the meta ones. It samples
    whole episodes per task, so POCA's batch sizes (accepted for a common launch
    signature) do not apply."""
    config = poca_config(env_config, base=MetaPOCAConfig(), train_batch_size=1,
                         minibatch_size=1, **poca_kwargs)
    return config.meta(tasks=tasks, episodes=episodes, inner_steps=inner_steps,
                       inner_lr=inner_lr, order=order, epochs=meta_epochs,
                       task_pool=task_pool)
