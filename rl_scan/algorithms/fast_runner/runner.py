"""``FastEnvRunner``: RLlib's MultiAgentEnvRunner with a batched sampling loop.

Why: the profile in docs/performance.md. RLlib's loop spends most of its time per env
step and per agent in Python: connector pipelines, episode objects, per-agent metrics
logging, and a module forward pass on a few rows with two OpenMP threads (which, on two
busy cores, costs several times the single-threaded pass). This runner keeps RLlib's
``sample()`` (timers, explore default, fragment length, ``on_sample_end``),
``get_metrics()``, state, checkpoints, spaces and modules, and replaces ``_sample``:

* it steps the ``ScanCore`` of every vector slot through its public reset/step API,
* runs one forward pass per module per step over all of its agents in all acting worlds
  (``acting.py``, torch limited to one thread while sampling),
* writes observations, actions, model outputs and rewards into preallocated arrays
  (``timelines.py``) and builds ``MultiAgentEpisode``s in bulk when the call ends
  (``episodes.py``): done episodes, then the chunks of ongoing ones, which continue in
  the next call exactly as the stock runner's ``cut()`` successors do.

Resets follow the stock runner: seeded on the first call and after every
``num_episodes`` call, a finished world resets at the next step (gymnasium's
"next_step" autoreset), so the same seed gives the same batches as RLlib's runner.
"""

from __future__ import annotations

import time
from contextlib import contextmanager

import numpy as np
import torch
from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner
from ray.rllib.env.multi_agent_episode import MultiAgentEpisode
from ray.rllib.utils.annotations import override
from ray.rllib.utils.metrics import (
    ENV_RESET_TIMER,
    ENV_STEP_TIMER,
    NUM_AGENT_STEPS_SAMPLED,
    NUM_AGENT_STEPS_SAMPLED_LIFETIME,
    NUM_ENV_STEPS_SAMPLED,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    NUM_EPISODES,
    NUM_EPISODES_LIFETIME,
    NUM_MODULE_STEPS_SAMPLED,
    NUM_MODULE_STEPS_SAMPLED_LIFETIME,
    RLMODULE_INFERENCE_TIMER,
)

from rl_scan.algorithms.fast_runner.acting import BatchedPolicy, modules_in_eval_mode
from rl_scan.algorithms.fast_runner.episodes import Chunk, build_episode
from rl_scan.algorithms.fast_runner.support import check_fast_sampler
from rl_scan.algorithms.fast_runner.team import TeamSlots
from rl_scan.algorithms.fast_runner.timelines import Timelines
from rl_scan.config import fail
from rl_scan.envs.rllib_env import ScanMultiAgentEnv


@contextmanager
def torch_threads(n: int):
    """Run torch with ``n`` intra-op threads inside the block (the learner keeps its own)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class FastEnvRunner(MultiAgentEnvRunner):
    """A MultiAgentEnvRunner for ``ScanMultiAgentEnv`` that samples all worlds in batches."""

    @override(MultiAgentEnvRunner)
    def __init__(self, config, **kwargs):
        check_fast_sampler(config)
        super().__init__(config=config, **kwargs)

    @override(MultiAgentEnvRunner)
    def make_env(self) -> None:
        """RLlib's vector env (so spaces, ``set_task`` and callbacks stay as they are),
        plus direct handles on the ScanCore in every vector slot."""
        super().make_env()
        envs = [e.unwrapped for e in self.env.unwrapped.envs]
        if not all(isinstance(e, ScanMultiAgentEnv) for e in envs):
            fail("sampler", "fast", f"'rllib' for {type(envs[0]).__name__} (the fast sampler "
                                    "steps ScanMultiAgentEnv worlds only)")
        self.worlds = [e.core for e in envs]
        first = envs[0]
        probe = MultiAgentEpisode(agent_to_module_mapping_fn=self.config.policy_mapping_fn)
        self.team = TeamSlots.of(first.possible_agents, probe.module_for,
                                 first.observation_spaces, first.action_spaces)
        self.spaces_of_agents = (dict(first.observation_spaces), dict(first.action_spaces))
        self.timelines = Timelines(self.team, len(self.worlds))
        self.chunks: list[Chunk | None] = [None] * len(self.worlds)
        self.pending_reset = np.zeros(len(self.worlds), bool)

    @override(MultiAgentEnvRunner)
    def _sample(self, *, num_timesteps: int | None = None, num_episodes: int | None = None,
                explore: bool, random_actions: bool = False,
                force_reset: bool = False) -> list[MultiAgentEpisode]:
        if random_actions:
            fail("random_actions", True, "False with sampler='fast' (use sampler='rllib')")
        if force_reset or num_episodes is not None or self._needs_initial_reset:
            self._reset_worlds(seed=self._seed if self._needs_initial_reset else None)
            self._needs_initial_reset = False
        if num_episodes is not None:
            self._needs_initial_reset = True
        actors = [self.module[m] for m in self.team.modules]
        with torch_threads(1), torch.inference_mode(), modules_in_eval_mode(actors):
            done, stats = self._run(num_timesteps, num_episodes, explore)
        ongoing = self._cut_ongoing() if num_timesteps is not None else []
        self._log_sample_metrics(stats)
        self._done_episodes_for_metrics.extend(done)
        return done + ongoing

    # ------------------------------------------------------------------ loop
    def _run(self, num_timesteps, num_episodes, explore) -> tuple[list, dict]:
        """Step until ``num_timesteps`` env (or agent) steps or ``num_episodes`` episodes."""
        policy = BatchedPolicy(self.module, self.team,
                               normalize_actions=self.config.normalize_actions,
                               clip_actions=self.config.clip_actions)
        by_agents = self.config.count_steps_by == "agent_steps"
        per_step = len(self.team.agent_ids) if by_agents else 1
        runners = self.config.num_env_runners or 1
        stats = {"env_steps": 0, "episodes": 0, "env_s": 0.0, "module_s": 0.0, "iterations": 0}
        done: list[MultiAgentEpisode] = []
        target = num_timesteps if num_timesteps is not None else 0
        self.timelines.reserve(-(-target // (per_step * len(self.worlds))) + 2)
        while (len(done) < num_episodes if num_timesteps is None
               else stats["env_steps"] * per_step < target):
            stepped = stats["env_steps"]
            t = (self.num_env_steps_sampled_lifetime // runners + stepped) * runners
            self.timelines.reserve(1)
            resetting = np.flatnonzero(self.pending_reset)
            acting = np.flatnonzero(~self.pending_reset)
            if len(acting):
                t0 = time.perf_counter()
                actions = policy.act(self.timelines.current_obs(acting), explore=explore, t=t,
                                     weights_seq_no=self._weights_seq_no)
                stats["module_s"] += time.perf_counter() - t0
                self.timelines.write_actions(
                    acting, {m: a.actions for m, a in actions.items()},
                    {m: a.outputs for m, a in actions.items()})
                t0 = time.perf_counter()
                stats["episodes"] += self._step_worlds(acting, actions, done, num_episodes)
                stats["env_s"] += time.perf_counter() - t0
                stats["env_steps"] += len(acting)
            for w in resetting:
                self._start_episode(int(w), self.worlds[w].reset())
            stats["iterations"] += 1
        return done, stats

    def _step_worlds(self, acting, actions, done, num_episodes) -> int:
        """Step every acting world; finished episodes go to ``done`` until it holds
        ``num_episodes`` (all are counted, as the stock runner counts them)."""
        finished = 0
        rows = {m: len(r.agent_ids) for m, r in self.team.modules.items()}
        for i, w in enumerate(acting):
            action_dict = {aid: actions[mid].for_env[i * rows[mid] + row]
                           for aid, mid, row in self.team.slots}
            obs, rewards, terminated, truncated, infos = self.worlds[w].step(action_dict)
            self.timelines.write_step(w, obs, rewards, infos)
            if terminated or truncated:
                self.pending_reset[w] = True
                finished += 1
                if num_episodes is None or len(done) < num_episodes:
                    done.append(self._finish_episode(int(w), terminated, truncated))
        return finished

    def _reset_worlds(self, seed: int | None) -> None:
        """Reset every world (seeds ``seed + index``, as RLlib's vector env does)."""
        t0 = time.perf_counter()
        self.timelines.pos[:] = -1
        self.timelines.infos.clear()
        self._ongoing_episodes_for_metrics.clear()
        for w, world in enumerate(self.worlds):
            self._start_episode(w, world.reset(seed=None if seed is None else seed + w))
        self.metrics.log_value(ENV_RESET_TIMER, time.perf_counter() - t0)

    def _start_episode(self, world: int, obs: dict[str, np.ndarray]) -> None:
        self.chunks[world] = Chunk(world, self.timelines.write_obs(world, obs))
        self.pending_reset[world] = False

    def _episode(self, chunk: Chunk) -> MultiAgentEpisode:
        return build_episode(chunk, self.timelines, self.team,
                             observation_spaces=self.spaces_of_agents[0],
                             action_spaces=self.spaces_of_agents[1],
                             mapping_fn=self.config.policy_mapping_fn)

    def _finish_episode(self, world: int, terminated: bool,
                        truncated: bool) -> MultiAgentEpisode:
        chunk = self.chunks[world]
        chunk.end = int(self.timelines.pos[world])
        chunk.terminated, chunk.truncated = terminated, truncated
        episode = self._episode(chunk)
        # RLlib's helper reads episodes[world], as from its list of ongoing episodes
        self._make_on_episode_callback("on_episode_end", world, {world: episode})
        self.chunks[world] = None
        return episode

    def _cut_ongoing(self) -> list[MultiAgentEpisode]:
        """Chunks of the ongoing episodes, and their successors for the next call."""
        out = []
        for w, chunk in enumerate(self.chunks):
            if chunk is None:  # finished at the last step: resets at the next one
                self.timelines.clear(w)
                continue
            position = int(self.timelines.pos[w])
            if chunk.steps(position) > 0:
                chunk.end = position
                episode = self._episode(chunk)
                self._ongoing_episodes_for_metrics[episode.id_].append(episode)
                out.append(episode)
            successor = chunk.successor(self.config.episode_lookback_horizon, position)
            self.timelines.restart(w, position - successor.lookback)
            self.chunks[w] = successor
        return out

    # --------------------------------------------------------------- metrics
    def _log_sample_metrics(self, stats: dict) -> None:
        """What the stock runner logs per step and agent, logged once per call."""
        steps, episodes, m = stats["env_steps"], stats["episodes"], self.metrics
        m.log_value(NUM_ENV_STEPS_SAMPLED, steps, reduce="sum")
        m.log_value(NUM_ENV_STEPS_SAMPLED_LIFETIME, steps, reduce="lifetime_sum",
                    with_throughput=True)
        if episodes:
            m.log_value(NUM_EPISODES, episodes, reduce="sum")
            m.log_value(NUM_EPISODES_LIFETIME, episodes, reduce="lifetime_sum")
        for aid, mid, _ in self.team.slots:
            for key, lifetime, name in ((NUM_AGENT_STEPS_SAMPLED,
                                         NUM_AGENT_STEPS_SAMPLED_LIFETIME, aid),
                                        (NUM_MODULE_STEPS_SAMPLED,
                                         NUM_MODULE_STEPS_SAMPLED_LIFETIME, mid)):
                m.log_value((key, name), steps, reduce="sum")
                m.log_value((lifetime, name), steps, reduce="lifetime_sum")
        if stats["iterations"]:
            m.log_value(ENV_STEP_TIMER, stats["env_s"] / stats["iterations"])
            m.log_value(RLMODULE_INFERENCE_TIMER, stats["module_s"] / stats["iterations"])
        if steps:
            self._log_env_steps(metric=self._metrics_num_env_steps_sampled, num_steps=steps)
