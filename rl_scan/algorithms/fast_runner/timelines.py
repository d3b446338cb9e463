"""Every world's observations, actions, model outputs and rewards in preallocated arrays.

Each world has its own timeline of positions: position p holds an observation; the action,
model outputs and reward at index p belong to the transition p -> p + 1. An episode chunk
is a range of positions; after an episode ends, the world's next position holds the reset
observation of its next episode (the slot between them carries no transition). Arrays are
reused across ``sample()`` calls and grow by doubling when a call needs more positions.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rl_scan.algorithms.fast_runner.team import TeamSlots


class Timelines:
    """Per-module arrays indexed (world, agent row, position, ...) and the write heads."""

    def __init__(self, team: TeamSlots, num_worlds: int, capacity: int = 64):
        self.team, self.num_worlds, self.capacity = team, num_worlds, capacity
        self.pos = np.full(num_worlds, -1)
        """The last written position of every world (-1: nothing yet)."""
        w = num_worlds
        self.obs = {m: np.zeros((w, len(r.agent_ids), capacity + 1, *r.observation_space.shape),
                                np.float32) for m, r in team.modules.items()}
        self.current = {m: np.zeros((w, len(r.agent_ids), *r.observation_space.shape),
                                    np.float32) for m, r in team.modules.items()}
        self.actions = {m: np.zeros((w, len(r.agent_ids), capacity, *r.action_space.shape),
                                    np.float32) for m, r in team.modules.items()}
        self.outputs: dict[str, dict[str, np.ndarray]] = {m: {} for m in team.modules}
        self.rewards = np.zeros((w, len(team.agent_ids), capacity))
        self.infos: dict[tuple[int, int], dict[str, Any]] = {}
        """Non-empty per-agent infos by (world, position); all others are empty dicts."""

    # ----------------------------------------------------------------- writing
    def reserve(self, positions: int) -> None:
        """Room for every world to write ``positions`` more positions."""
        need = int(self.pos.max()) + positions + 1
        if need <= self.capacity:
            return
        capacity = max(need, 2 * self.capacity)

        def grown(a: np.ndarray, extra: int) -> np.ndarray:
            out = np.zeros((*a.shape[:2], capacity + extra, *a.shape[3:]), a.dtype)
            out[:, :, :a.shape[2]] = a
            return out

        self.obs = {m: grown(a, 1) for m, a in self.obs.items()}
        self.actions = {m: grown(a, 0) for m, a in self.actions.items()}
        self.outputs = {m: {k: grown(a, 0) for k, a in cols.items()}
                        for m, cols in self.outputs.items()}
        rewards = np.zeros((*self.rewards.shape[:2], capacity))
        rewards[:, :, :self.capacity] = self.rewards
        self.rewards, self.capacity = rewards, capacity

    def write_obs(self, world: int, obs: dict[str, np.ndarray]) -> int:
        """Append an observation of every agent to ``world``'s timeline; its position."""
        p = int(self.pos[world]) + 1
        self.pos[world] = p
        for aid, mid, row in self.team.slots:
            self.obs[mid][world, row, p] = self.current[mid][world, row] = obs[aid]
        return p

    def write_step(self, world: int, obs: dict[str, np.ndarray], rewards: dict[str, float],
                   infos: dict[str, dict]) -> None:
        """The outcome of the transition from ``world``'s last position."""
        self.rewards[world, :, self.pos[world]] = [rewards[aid] for aid in self.team.agent_ids]
        p = self.write_obs(world, obs)
        if any(infos.values()):
            self.infos[(world, p)] = infos

    def current_obs(self, worlds: np.ndarray) -> dict[str, np.ndarray]:
        """Every module's batch of current observations of ``worlds`` (world-major rows)."""
        all_worlds = len(worlds) == self.num_worlds
        return {m: (cur if all_worlds else cur[worlds]).reshape(-1, *cur.shape[2:])
                for m, cur in self.current.items()}

    def write_actions(self, worlds: np.ndarray, actions: dict[str, np.ndarray],
                      outputs: dict[str, dict[str, np.ndarray]]) -> None:
        """Actions and model outputs (world-major rows) at the current position of ``worlds``."""
        at = (worlds[:, None], None, self.pos[worlds][:, None])
        for mid, acts in actions.items():
            rows = len(self.team.modules[mid].agent_ids)
            index = (at[0], np.arange(rows)[None, :], at[2])
            self.actions[mid][index] = acts.reshape(len(worlds), rows, *acts.shape[1:])
            cols = self.outputs[mid]
            for key, value in outputs[mid].items():
                if key not in cols:
                    cols[key] = np.zeros((*self.actions[mid].shape[:3], *value.shape[1:]),
                                         value.dtype)
                cols[key][index] = value.reshape(len(worlds), rows, *value.shape[1:])

    def restart(self, world: int, start: int) -> None:
        """Move positions ``start..pos`` of ``world`` to the front (the next call's carry)."""
        end = int(self.pos[world])
        n = end - start
        for mid in self.obs:
            self.obs[mid][world, :, :n + 1] = self.obs[mid][world, :, start:end + 1].copy()
            self.actions[mid][world, :, :n] = self.actions[mid][world, :, start:end].copy()
            for col in self.outputs[mid].values():
                col[world, :, :n] = col[world, :, start:end].copy()
        self.rewards[world, :, :n] = self.rewards[world, :, start:end].copy()
        moved = {(w, p - start): v for (w, p), v in self.infos.items()
                 if w == world and start <= p <= end}
        self.infos = {k: v for k, v in self.infos.items() if k[0] != world} | moved
        self.pos[world] = n

    def clear(self, world: int) -> None:
        """Forget ``world``'s timeline (its next observation goes to position 0)."""
        self.pos[world] = -1
        self.infos = {k: v for k, v in self.infos.items() if k[0] != world}

    # ----------------------------------------------------------------- reading
    def agent_data(self, world: int, aid: str, start: int, end: int) -> dict[str, Any]:
        """Copies of one agent's data over positions ``start..end`` (end inclusive)."""
        mid, row = next((m, r) for a, m, r in self.team.slots if a == aid)
        i = self.team.agent_ids.index(aid)
        return {"observations": self.obs[mid][world, row, start:end + 1].copy(),
                "actions": self.actions[mid][world, row, start:end].copy(),
                "rewards": self.rewards[world, i, start:end].copy(),
                "extra_model_outputs": {k: col[world, row, start:end].copy()
                                        for k, col in self.outputs[mid].items()},
                "infos": [self.infos.get((world, p), {}).get(aid, {})
                          for p in range(start, end + 1)]}
