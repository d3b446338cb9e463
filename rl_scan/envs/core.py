"""Adapter-independent episode logic shared by the RLlib and PettingZoo envs.

``ScanCore`` owns the config, the (cached) worlds of the scenarios it has seen, the
episode counters and metrics. It validates actions, turns per-agent action dicts into
the simulator's action matrix and the simulator's outputs into per-agent dicts.
``reset(options={"scenario": "train:17"})`` switches scenario for domain randomisation
and meta-learning; ``scenario: train:*`` picks one of the 1000 training scenes per reset
(worlds are cached) and ``scenario: random`` draws a brand-new scene per reset.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from rl_scan import metrics as M
from rl_scan.envs.observations import action_spaces, kind_of, observation_spaces
from rl_scan.envs.sim.env_config import EnvConfig, make_env_config
from rl_scan.envs.sim.robots import ACTION_WIDTH, KINDS
from rl_scan.envs.sim.scenarios import N_TRAIN, load_scenario, parse_scenario_name
from rl_scan.envs.sim.world import World

WORLD_CACHE_SIZE = 64


RENDER_MODES = ("rgb_array",)


def split_render_mode(config: dict[str, Any] | None) -> tuple[dict[str, Any], str | None]:
    """Separate the adapter-level ``render_mode`` key from the EnvConfig mapping."""
    config = dict(config or {})
    mode = config.pop("render_mode", None)
    if mode not in (None, *RENDER_MODES):
        raise ValueError(f"render_mode={mode!r} is invalid: allowed None or {list(RENDER_MODES)}")
    return config, mode


class ScanCore:
    """One scanning environment: reset, step, metrics, render."""

    def __init__(self, config: dict[str, Any] | EnvConfig | None = None):
        self.config = make_env_config(config)
        self.agent_ids = self.config.team.agent_ids
        self.observation_spaces = observation_spaces(self.config)
        self.action_spaces = action_spaces(self.config)
        self._dims = {aid: self.observation_spaces[aid].shape[0] for aid in self.agent_ids}
        self._index = {aid: i for i, aid in enumerate(self.agent_ids)}
        self._action_shapes = [self.action_spaces[aid].shape for aid in self.agent_ids]
        self._kinds = np.array([kind_of(aid) for aid in self.agent_ids])
        self._worlds: OrderedDict[str, World] = OrderedDict()
        self._actions = np.zeros((len(self.agent_ids), ACTION_WIDTH))
        self.np_random = np.random.default_rng()
        self.scenario_name = self.config.scenario
        first = "train:0" if self.scenario_name == "train:*" else self.scenario_name
        self.world = self._world(first)  # fail fast on a bad scenario
        self.done = True
        self.lifetime_steps = 0  # over all episodes: what fault_at_step counts

    # ------------------------------------------------------------------ worlds
    def _world(self, name: str) -> World:
        if name == "random":
            cfg = self.config
            scenario = load_scenario("random", cfg.scenario_distribution, np.array(cfg.arena),
                                     cfg.cell_size, rng=self.np_random)
            return World(cfg, scenario)
        if name not in self._worlds:
            cfg = self.config
            scenario = load_scenario(name, cfg.scenario_distribution, np.array(cfg.arena),
                                     cfg.cell_size)
            self._worlds[name] = World(cfg, scenario)
            if len(self._worlds) > WORLD_CACHE_SIZE:
                self._worlds.popitem(last=False)
        self._worlds.move_to_end(name)
        return self._worlds[name]

    # ----------------------------------------------------------------- episode
    def reset(self, seed: int | None = None,
              options: dict[str, Any] | None = None) -> dict[str, np.ndarray]:
        """Start an episode; ``options={'scenario': name}`` switches the scenario first."""
        if seed is not None:
            self.np_random = np.random.default_rng(seed)
        scenario = (options or {}).get("scenario")  # other options are ignored (gymnasium)
        if scenario is not None:
            self.set_scenario(scenario)
        name = self.scenario_name
        if name == "train:*":
            name = f"train:{int(self.np_random.integers(N_TRAIN))}"
        self.world = self._world(name)
        self.world_name = name  # the scene drawn (``train:*`` names one train scene)
        obs = self.world.reset(self.np_random)
        self.t = 0
        self.done = False
        n = len(self.agent_ids)
        self.returns = np.zeros(n)
        self.collisions = np.zeros(n, dtype=np.int64)
        self.steps_to = {frac: float("nan") for frac in M.STEPS_TO}
        self._thresholds = sorted(M.STEPS_TO)
        return self._split(obs)

    def set_scenario(self, name: str) -> None:
        """Use scenario ``name`` from the next reset on (validated now)."""
        self.scenario_name = parse_scenario_name(str(name))

    def to_action_matrix(self, action_dict: dict[str, Any]) -> np.ndarray:
        """Validate per-agent actions and place them in the simulator's (n, ACTION_WIDTH) matrix.

        A kind's action is a prefix of the simulator's (forward, left, yaw, up, pitch).
        Missing agents act with zeros; actions are clipped to [-1, 1] (as ML-Agents does).
        """
        acts = self._actions
        acts[:] = 0.0
        for aid, a in action_dict.items():
            i = self._index.get(aid)
            if i is None:
                raise ValueError(f"action for unknown agent {aid!r}: agents are "
                                 f"{self.agent_ids}")
            shape = self._action_shapes[i]
            if getattr(a, "shape", None) != shape:
                a = np.asarray(a, dtype=np.float64)
                if a.shape != shape:
                    raise ValueError(f"action of {aid!r} has shape {a.shape}: expected {shape} "
                                     f"(values in [-1, 1])")
            acts[i, :shape[0]] = a
        if not np.isfinite(acts).all():
            bad = self.agent_ids[int(np.flatnonzero(~np.isfinite(acts).all(axis=1))[0])]
            raise ValueError(f"action of {bad!r} is not finite: "
                             f"{np.asarray(action_dict[bad]).tolist()}; allowed values in [-1, 1]")
        np.clip(acts, -1.0, 1.0, out=acts)
        return acts

    def step(self, action_dict: dict[str, Any]):
        """Advance one step: (obs, rewards, terminated, truncated, infos); flags are bools."""
        if self.done:
            raise RuntimeError("step() called on a finished episode: call reset() first")
        acts = self.to_action_matrix(action_dict)
        world = self.world
        obs = world.step(acts)
        cfg = self.config
        hit = world.collided != 0
        rewards = cfg.scan_reward * world.new_cells - cfg.collision_penalty * hit
        if cfg.reward_mode == "team":
            rewards = np.full(len(rewards), rewards.sum())
        self.returns += rewards
        self.collisions += hit
        self.t += 1
        self.lifetime_steps += 1
        if self.lifetime_steps == cfg.fault_at_step and self._inject_fault():
            rewards = np.full(len(rewards), np.nan)
        scanned = world.n_scanned
        while self._thresholds and scanned >= self._thresholds[0] * world.n_cells:
            self.steps_to[self._thresholds.pop(0)] = float(self.t)
        terminated = scanned == world.n_cells
        truncated = not terminated and self.t >= cfg.max_steps
        self.done = terminated or truncated
        rew = {aid: float(r) for aid, r in zip(self.agent_ids, rewards)}
        infos = {aid: {} for aid in self.agent_ids}
        if self.done:
            summary = self.episode_metrics()
            for aid in self.agent_ids:
                infos[aid] = {"episode_metrics": summary, "scenario": self.world_name}
        return self._split(obs), rew, terminated, truncated, infos

    def _inject_fault(self) -> bool:
        """Raise, or return True for a NaN reward (EnvConfig.fault_*), at most once with a
        ``fault_once_file``: lets tests exercise fault tolerance and the NaN guard."""
        marker = Path(self.config.fault_once_file) if self.config.fault_once_file else None
        if marker is not None and marker.exists():
            return False
        if marker is not None:
            marker.touch()
        if self.config.fault_kind == "nan_reward":
            return True
        raise RuntimeError(f"injected env fault at step {self.lifetime_steps} of this env "
                           "(fault_at_step)")

    def _split(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        return {aid: obs[i, :self._dims[aid]].copy() for i, aid in enumerate(self.agent_ids)}

    def episode_metrics(self) -> dict[str, float]:
        """Coverage, success, steps to 50/80/95 %, collisions and returns so far."""
        world = self.world
        coverage = world.n_scanned / world.n_cells
        out = {M.COVERAGE: coverage, M.SUCCESS: float(coverage >= M.SUCCESS_COVERAGE),
               M.COLLISIONS: float(self.collisions.sum()), M.EPISODE_STEPS: float(self.t),
               M.CELLS_SCANNED: float(world.n_scanned), M.CELLS_TOTAL: float(world.n_cells)}
        for frac, key in M.STEPS_TO.items():
            out[key] = self.steps_to[frac]
        for kind in KINDS:
            mine = self._kinds == kind
            out[M.COLLISIONS_BY_KIND[kind]] = float(self.collisions[mine].sum())
            out[M.RETURN_BY_KIND[kind]] = float(self.returns[mine].mean()) if mine.any() else 0.0
        return out

    def render_rgb(self) -> np.ndarray:
        """An RGB frame (top view and side view) of the current state."""
        from rl_scan.envs.render import render_frame

        return render_frame(self.world, self.t)
