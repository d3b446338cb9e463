"""meta-MRSS (the paper's Algorithm 1) as first-order MAML-PPO over POCA, on all its data.

Per meta-iteration, for each of ``meta_tasks`` distinct train scenarios (task i):
  1. sample ``support_steps`` env steps with the meta policy theta (fresh episodes);
  2. inner loop: ``inner_updates`` ordinary POCA updates on that support batch (the
     preset's epochs and minibatches, Adam at POCA's lr x ``inner_lr`` from a fresh state,
     actors and critic) give theta'_i and delta_i = theta'_i - theta; the learner returns to theta;
  3. sample ``query_steps`` env steps with theta'_i.
With ``sampling='shared'`` step 1 is DR's: one batch of ``support_steps`` with theta on the
runner's envs (``train:*``, episodes continued across meta-iterations) is theta's batch,
and the tasks are ``meta_tasks`` of its whole episodes (their scenes); step 3 runs on a
one-env side runner so that DR's episodes go on.
Then the outer update (``outer``):
  * ``maml``: one ordinary POCA update at theta on theta's batch (every task's support
    batch; with ``shared`` sampling DR's batch: the gradient DR takes from it), then per
    task one on its query batch at theta + delta_i (advantages from the adapted critic):
    each minibatch is one meta-Adam step with the first-order MAML gradient, clipped
    against the policy that sampled it;
  * ``maml_dr``: as ``maml``, but the update at theta learns from every support and query
    batch (tasks mixed: the DR update on all the data) before the per-task query updates
    at theta + delta_i (the MAML term added to DR's objective);
  (``maml_weight`` scales the lr of the updates at theta + delta_i: the MAML term's weight;
  ``maml_step='mean'`` makes them one meta-Adam step per minibatch on the mean over tasks;
  ``relabel_query`` makes the update at theta clip the query rows around theta, and
  ``query_importance`` weighs them by pi_theta / pi_theta'_i);
  * ``reptile``: theta += reptile_lr * mean_i(theta''_i - theta), theta''_i being theta'_i
    after one more POCA update on the task's query batch;
  * ``multitask`` (a control): one ordinary POCA update at theta on all support and query
    batches together (tasks mixed in every minibatch): domain randomisation on the same data.
Every sampled env step is learned from, and counted once (the budget is exact).
The task work (inner updates, queries, the MAML term) draws its random numbers from its own
streams (``random_streams``): theta's sampling and update draw exactly DR's, so with
``maml_weight=0`` and ``outer='maml'`` the shared layout's theta is DR's, tensor for tensor.

    config = meta_poca_config({"max_steps": 200}, tasks=4, support_steps=800, query_steps=800)
    algo = config.build_algo(); algo.train(); algo.save_to_path("ckpt")

Sampling runs on the local env runner (``num_env_runners=0``): tasks are set per env and
adapted actors are loaded between support and query sampling.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from ray.rllib.algorithms.algorithm_config import NotProvided
from ray.rllib.utils.annotations import override
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    ENV_RUNNER_SAMPLING_TIMER,
    LEARNER_RESULTS,
    LEARNER_UPDATE_TIMER,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    TIMERS,
)

from rl_scan.algorithms.callbacks import episode_scenario, episode_summary
from rl_scan.algorithms.maml.learners import Key, MetaPOCALearner
from rl_scan.algorithms.maml.random_streams import own_random_streams
from rl_scan.algorithms.maml.settings import MetaSettings
from rl_scan.algorithms.poca.modules import CRITIC_ID
from rl_scan.algorithms.poca.poca import POCA, POCAConfig, poca_config
from rl_scan.config import check_range, fail
from rl_scan.envs.sim.env_config import EnvConfig
from rl_scan.envs.sim.scenarios import N_TRAIN
from rl_scan.results import (
    META_AFTER,
    META_BEFORE,
    META_DELTA_COSINE,
    META_DELTA_NORM,
    META_TERM_RESULTS,
)

# the ``own_random_streams`` key's phase: which task work draws from the stream
ADAPT_PHASE, MAML_TERM_PHASE, SIDE_RUNNER_PHASE = range(3)

CONFIG_ATTRS = {"tasks": "meta_tasks", "outer": "outer_rule"}
"""MetaSettings fields whose MetaPOCAConfig attribute has another name."""
META_KEYWORDS = (*(f.name for f in fields(MetaSettings)), "task_pool")
"""The meta settings ``MetaPOCAConfig.meta`` and ``meta_poca_config`` take."""


class MetaPOCAConfig(POCAConfig):
    """POCAConfig plus the meta-learning settings (``meta()``; paper: tau=10, K=20)."""

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or MetaPOCA)
        self.meta_tasks = 10
        self.support_steps = 10_000
        self.query_steps = 10_000
        self.inner_updates = 1
        self.inner_lr = 1.0
        self.inner_adam = "fresh"
        self.outer_rule = "maml"
        self.reptile_lr = 1.0
        self.maml_weight = 1.0
        self.relabel_query = False
        self.query_importance = False
        self.sampling = "per_task"
        self.maml_step = "per_task"
        self.task_envs = 0
        self.task_pool = N_TRAIN

    def meta(self, **settings: Any) -> MetaPOCAConfig:
        """Meta settings by name: the fields of ``MetaSettings`` (which documents each) and
        ``task_pool`` (tasks are drawn from ``train:0`` .. ``train:{task_pool - 1}``)."""
        for name, value in settings.items():
            if name not in META_KEYWORDS:
                fail("meta", name, f"one of {list(META_KEYWORDS)}")
            if value is not NotProvided:
                setattr(self, CONFIG_ATTRS.get(name, name), value)
        return self

    @override(POCAConfig)
    def get_default_learner_class(self):
        return MetaPOCALearner

    def settings(self) -> MetaSettings:
        """The meta settings as ``MetaSettings`` (which holds their documentation and rules)."""
        return MetaSettings(**{f.name: getattr(self, CONFIG_ATTRS.get(f.name, f.name))
                               for f in fields(MetaSettings)})

    @override(POCAConfig)
    def validate(self) -> None:
        self.settings().validate("meta.")
        check_range("meta.task_pool", self.task_pool, 1, N_TRAIN)
        check_range("meta.tasks", self.meta_tasks, 1, self.task_pool)  # distinct tasks
        if self.task_envs and self.task_envs != self.num_envs_per_env_runner:
            fail("meta.task_envs", self.task_envs, "0 or num_envs_per_env_runner="
                 f"{self.num_envs_per_env_runner} (meta_poca_config sets it from task_envs)")
        self.settings().check_steps_fit(self.num_envs_per_env_runner, "meta.",
                                        max_steps=int(self.env_config.get("max_steps", 0)))
        if self.num_env_runners != 0:
            fail("num_env_runners", self.num_env_runners,
                 "0 (MetaPOCA samples its tasks on the local env runner)")
        for name in ("entropy_coeff", "lr"):
            if not isinstance(getattr(self, name), (int, float)):
                fail(name, getattr(self, name), "a constant for MetaPOCA (no schedule)")
        super().validate()


def set_task(env_runner, scenario: str) -> None:
    """Every env of a (local) env runner uses ``scenario`` from its next reset on."""
    for env in env_runner.env.unwrapped.envs:
        env.unwrapped.set_task(scenario)


def mean_coverage(episodes: list) -> float:
    """Mean final coverage of the finished episodes (chunks cut by sampling have none)."""
    values = [s["coverage"] for s in map(episode_summary, episodes) if s is not None]
    return float(np.mean(values)) if values else float("nan")


@dataclass
class Task:
    """One task of a meta-iteration: its batches and the inner update's delta."""

    scenario: str
    support: list
    query: list
    delta: dict[Key, torch.Tensor]


class MetaPOCA(POCA):
    """meta-MRSS: first-order MAML-PPO (or Reptile) over POCA (see the module doc)."""

    _side_runner = None  # the ``shared`` layout's query runner, built on first use

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
        learner: MetaPOCALearner = self.learner_group._learner  # num_learners=0: local
        actor_ids = [mid for mid in runner.module.keys() if mid != CRITIC_ID]
        meta_actors = {mid: copy.deepcopy(runner.module[mid].state_dict())
                       for mid in actor_ids}
        if cfg.sampling == "shared":
            at_theta, tasks = self._shared_tasks(learner, meta_actors)
            runners = [runner, self._query_runner()]
        else:
            at_theta, tasks = self._per_task_tasks(learner, meta_actors)
            runners = [runner]
        self.metrics.aggregate([r.get_metrics() for r in runners], key=ENV_RUNNER_RESULTS)
        # diagnostics: the adaptation gain (query episodes with theta'_i vs the tasks'
        # support episodes with theta) and how far the inner update moves the parameters
        self.metrics.log_value(META_BEFORE, mean_coverage(
            [e for t in tasks for e in t.support]), window=1)
        self.metrics.log_value(META_AFTER, mean_coverage(
            [e for t in tasks for e in t.query]), window=1)
        self.metrics.log_value(META_DELTA_NORM, float(np.mean(
            [delta_norm(learner, t.delta) for t in tasks])), window=1)
        self.metrics.log_value(META_DELTA_COSINE, delta_cosine(
            [t.delta for t in tasks], parameter_keys(learner)), window=1)
        with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
            results = self._outer_update(learner, at_theta, tasks)
        # The update at theta is DR's on the same data, so its results (the critic's
        # explained variance included) stand where POCA's do; merged with the MAML term's
        # single-task updates at theta + delta_i, RLlib would log the mean of them all.
        self.metrics.aggregate(results[:1], key=LEARNER_RESULTS)
        if results[1:]:
            self.metrics.aggregate(results[1:], key=META_TERM_RESULTS)
        self.env_runner_group.sync_weights(from_worker_or_learner_group=self.learner_group,
                                           policies=actor_ids, inference_only=True)

    def _per_task_tasks(self, learner: MetaPOCALearner, meta_actors: dict
                        ) -> tuple[list, list[Task]]:
        """``sampling='per_task'``: each task's support and query from fresh episodes of
        its scene on the runner; theta's batch is every support batch."""
        cfg = self.config
        runner = self.env_runner
        tasks = []
        for index, scenario in enumerate(self.meta_tasks_of(self.iteration)):
            set_task(runner, scenario)
            support = self._sample(runner, meta_actors, cfg.support_steps)
            tasks.append(self._adapted_task(learner, runner, scenario, support, index))
        set_task(runner, cfg.env_config.get("scenario", "ablation"))
        return [e for t in tasks for e in t.support], tasks

    def _shared_tasks(self, learner: MetaPOCALearner, meta_actors: dict
                      ) -> tuple[list, list[Task]]:
        """``sampling='shared'``: DR's batch with theta (episodes continued), the tasks
        drawn from its whole episodes, each query on the side runner."""
        cfg = self.config
        with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
            self._load_actors(self.env_runner, meta_actors)
            batch = self.env_runner.sample(num_timesteps=cfg.support_steps)
        whole = [e for e in batch if e.is_done and e.env_t_started == 0]
        rng = np.random.default_rng([cfg.seed or 0, self.iteration])
        picked = rng.choice(len(whole), size=min(cfg.meta_tasks, len(whole)), replace=False)
        side = self._query_runner()
        tasks = []
        for index, i in enumerate(sorted(picked)):
            scenario = episode_scenario(whole[int(i)])
            set_task(side, scenario)
            tasks.append(self._adapted_task(learner, side, scenario, [whole[int(i)]], index))
        return batch, tasks

    def _adapted_task(self, learner: MetaPOCALearner, runner, scenario: str,
                      support: list, index: int) -> Task:
        """The inner update on ``support`` (theta'_i, delta_i), then the query batch sampled
        by theta'_i on ``runner`` (set to ``scenario``) from fresh episodes; task ``index``'s
        own random streams."""
        cfg = self.config
        with self._task_streams(ADAPT_PHASE, index):
            with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
                delta, adapted, _ = learner.adapt(support, self._timesteps(),
                                                  cfg.inner_updates, adam=cfg.inner_adam,
                                                  lr_scale=cfg.inner_lr)
            query = self._sample(runner, adapted, cfg.query_steps)
        return Task(scenario, support, query, delta)

    def _task_streams(self, phase: int, index: int = 0):
        """``own_random_streams`` of this run, meta-iteration, phase and task."""
        return own_random_streams(self.config.seed or 0, self.iteration, phase, index)

    def _query_runner(self):
        """The one-env runner the ``shared`` layout samples queries on (built once; its own
        env seeds: worker index 1). RLlib's EnvRunner seeds the process's random, numpy
        and torch generators when built (seed + worker index, the next seed's main one);
        inside ``_task_streams`` they come back as they were."""
        if self._side_runner is None:
            config = self.config.copy(copy_frozen=False)
            config.num_envs_per_env_runner = 1
            with self._task_streams(SIDE_RUNNER_PHASE):
                self._side_runner = type(self.env_runner)(config=config, worker_index=1,
                                                          num_workers=1)
        return self._side_runner

    @override(POCA)
    def cleanup(self) -> None:
        if self._side_runner is not None:
            self._side_runner.stop()
        super().cleanup()

    def _outer_update(self, learner: MetaPOCALearner, at_theta: list,
                      tasks: list[Task]) -> list[dict]:
        """The meta update on every sampled step (see the module doc): ``at_theta`` is
        theta's own batch; the episodes are the update's from here (RLlib's learner
        connectors extend them in place)."""
        timesteps = self._timesteps()
        if self.config.outer_rule == "reptile":
            with self._task_streams(MAML_TERM_PHASE):
                deltas = [learner.adapt(t.query, timesteps, 1, start=t.delta)[0]
                          for t in tasks]
            learner.reptile_step(deltas, self.config.reptile_lr)
            return []
        kwargs = learner.update_kwargs(timesteps)
        rule = self.config.outer_rule
        at_theta = list(at_theta)
        if rule in ("multitask", "maml_dr"):  # every batch at theta, tasks mixed
            query = [e for t in tasks for e in t.query]
            query = query if rule == "multitask" else copy.deepcopy(query)
            if self.config.relabel_query:
                learner.relabel_behaviour(query)
            at_theta += query
        results = [learner.update(episodes=at_theta, **kwargs)]
        if rule == "multitask" or self.config.maml_weight == 0:
            return results
        with self._task_streams(MAML_TERM_PHASE):
            if self.config.maml_step == "mean":
                with learner.lr_scaled(self.config.maml_weight):
                    results.append(learner.mean_shifted_update(
                        [(t.query, t.delta) for t in tasks], **kwargs))
                return results
            for task in tasks:  # the critic learns at theta only, where tasks are mixed
                with (learner.shifted(task.delta),
                      learner.lr_scaled(self.config.maml_weight), learner.critic_frozen()):
                    results.append(learner.update(episodes=task.query, **kwargs))
        return results

    def _sample(self, runner, actors: dict[str, dict[str, torch.Tensor]], steps: int) -> list:
        """``steps`` env steps with ``actors``, from fresh episodes (all of it kept)."""
        with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
            self._load_actors(runner, actors)
            return runner.sample(num_timesteps=steps, force_reset=True)

    def _timesteps(self) -> dict[str, Any]:
        return {NUM_ENV_STEPS_SAMPLED_LIFETIME: self.metrics.peek(
            (ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0)}

    @staticmethod
    def _load_actors(runner, state: dict[str, dict[str, torch.Tensor]]) -> None:
        for mid, sd in state.items():
            runner.module[mid].load_state_dict(sd)


def parameter_keys(learner: MetaPOCALearner) -> list[Key]:
    """The keys of a delta that are parameters (not the critic's return moments)."""
    return sorted((mid, n) for mid in learner.module.keys()
                  for n, _ in learner.module[mid].named_parameters())


def delta_norm(learner: MetaPOCALearner, delta: dict[Key, torch.Tensor]) -> float:
    """||delta|| over the parameters (not the return moments)."""
    return float(torch.sqrt(sum((delta[k] * delta[k]).sum() for k in parameter_keys(learner))))


def delta_cosine(deltas: list[dict[Key, torch.Tensor]], keys: list[Key]) -> float:
    """Mean cosine similarity over pairs of the tasks' deltas (over ``keys``; nan with one
    task): near 1, the inner update moves every scene's policy the same way (e.g. along
    the meta optimizer's momentum), not towards what its scene rewards."""
    if len(deltas) < 2:
        return float("nan")
    flat = torch.stack([torch.cat([d[k].flatten() for k in keys]) for d in deltas])
    unit = flat / flat.norm(dim=1, keepdim=True).clamp_min(1e-12)
    cos = unit @ unit.T
    n = len(deltas)
    return float((cos.sum() - cos.diagonal().sum()) / (n * (n - 1)))


def meta_poca_config(env_config: EnvConfig | dict[str, Any], *, train_batch_size: int = 4_000,
                     minibatch_size: int = 1_024, **kwargs: Any) -> MetaPOCAConfig:
    """MetaPOCAConfig for the scanning env: POCA's settings (its minibatch size and epochs
    serve the inner and outer updates) plus the meta ones, the keywords of
    ``MetaPOCAConfig.meta`` (defaults: the paper's, in ``MetaPOCAConfig``).
    ``train_batch_size`` is accepted for a common launch signature; a meta-iteration
    samples ``tasks * (support_steps + query_steps)`` env steps instead; ``task_envs``
    (if not 0) replaces ``num_envs_per_env_runner``."""
    meta = {k: kwargs.pop(k) for k in list(kwargs) if k in META_KEYWORDS}
    if meta.get("task_envs", 0) > 0:
        kwargs["num_envs_per_env_runner"] = meta["task_envs"]
    config = poca_config(env_config, base=MetaPOCAConfig(), train_batch_size=train_batch_size,
                         minibatch_size=minibatch_size, **kwargs)
    return config.meta(**meta)
