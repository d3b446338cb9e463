"""RLlib ``MultiAgentEpisode``s built in bulk from a world's timeline.

A chunk is the part of one world's episode that a ``sample()`` call returns. Chunks are
built as the stock runner leaves them after ``to_numpy()``: numpy data, the first
``lookback`` transitions (``episode_lookback_horizon``, carried from the previous chunk
as ``MultiAgentEpisode.cut`` does) in the lookback buffers, the same episode and agent
episode ids across the chunks of one episode, and RLlib 2.60's flags: a multi-agent
episode whose agents are all done counts as terminated, truncated or not, and so does
each of its agents.
"""

from __future__ import annotations

import time
import uuid
from collections import defaultdict
from dataclasses import dataclass, field

from ray.rllib.env.multi_agent_episode import MultiAgentEpisode
from ray.rllib.env.single_agent_episode import SingleAgentEpisode
from ray.rllib.env.utils.infinite_lookback_buffer import InfiniteLookbackBuffer

from rl_scan.algorithms.fast_runner.team import TeamSlots
from rl_scan.algorithms.fast_runner.timelines import Timelines


@dataclass
class Chunk:
    """Positions ``start..end`` of a world's timeline; the first ``lookback`` transitions
    belong to the previous chunk of the same episode."""

    world: int
    start: int
    env_t_started: int = 0
    lookback: int = 0
    episode_id: str = field(default_factory=lambda: uuid.uuid4().hex)
    agent_episode_ids: dict[str, str] = field(default_factory=dict)
    started_at: float = field(default_factory=time.perf_counter)
    end: int = -1
    terminated: bool = False
    truncated: bool = False

    def steps(self, position: int) -> int:
        """Env steps of this chunk (lookback excluded) if it ends at ``position``."""
        return position - self.start - self.lookback

    def successor(self, lookback_horizon: int, position: int) -> Chunk:
        """The next chunk of this ongoing episode, for a timeline restarted at its first
        lookback position. As ``MultiAgentEpisode.cut``: up to ``lookback_horizon``
        transitions of lookback, taken from this chunk including its own lookback."""
        lookback = min(lookback_horizon, position - self.start)
        return Chunk(self.world, 0, self.env_t_started + self.steps(position), lookback,
                     self.episode_id, self.agent_episode_ids)


def build_episode(chunk: Chunk, timelines: Timelines, team: TeamSlots, *,
                  observation_spaces: dict, action_spaces: dict,
                  mapping_fn) -> MultiAgentEpisode:
    """The MultiAgentEpisode of ``chunk`` (copies of the timeline's data)."""
    done = chunk.terminated or chunk.truncated
    module_ids = {aid: mid for aid, mid, _ in team.slots}
    episode = MultiAgentEpisode(
        id_=chunk.episode_id, observation_space=observation_spaces,
        action_space=action_spaces, agent_to_module_mapping_fn=mapping_fn,
        agent_module_ids=dict(module_ids), env_t_started=chunk.env_t_started)
    steps = chunk.steps(chunk.end)
    t0 = chunk.env_t_started
    for aid in team.agent_ids:
        data = timelines.agent_data(chunk.world, aid, chunk.start, chunk.end)
        sa_id = chunk.agent_episode_ids.setdefault(aid, uuid.uuid4().hex)
        episode.agent_episodes[aid] = SingleAgentEpisode(
            id_=sa_id, agent_id=aid, module_id=module_ids[aid],
            multi_agent_episode_id=chunk.episode_id,
            observation_space=observation_spaces[aid], action_space=action_spaces[aid],
            terminated=done, truncated=chunk.truncated, t_started=t0,
            len_lookback_buffer=chunk.lookback, **data)
        episode.env_t_to_agent_t[aid] = InfiniteLookbackBuffer(
            list(range(t0 - chunk.lookback, t0 + steps + 1)), lookback=chunk.lookback)
    episode.agent_t_started = defaultdict(int, dict.fromkeys(team.agent_ids, t0))
    episode.env_t = t0 + steps
    episode.is_terminated, episode.is_truncated = done, chunk.truncated
    episode._start_time, episode._last_step_time = chunk.started_at, time.perf_counter()
    return episode
