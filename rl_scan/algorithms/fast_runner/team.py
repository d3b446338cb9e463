"""Where each robot's data lives in the fast sampler's arrays: one row block per module."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from rl_scan.config import fail


@dataclass(frozen=True)
class ModuleRows:
    """The agents one policy module acts for, in team order, and their (shared) spaces."""

    module_id: str
    agent_ids: tuple[str, ...]
    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box


@dataclass(frozen=True)
class TeamSlots:
    """Agents in team order, grouped into module row blocks.

    ``slots`` lists (agent id, module id, row within the module's block) in team order:
    the row of agent j of world w in a module's batch is ``w * len(block) + j``.
    """

    agent_ids: tuple[str, ...]
    modules: dict[str, ModuleRows]
    slots: tuple[tuple[str, str, int], ...]

    @classmethod
    def of(cls, agent_ids, module_of, observation_spaces, action_spaces) -> TeamSlots:
        """``module_of(agent_id)`` maps agents to modules once: the scanning team's mapping
        is by robot kind, fixed for a run."""
        blocks: dict[str, list[str]] = {}
        for aid in agent_ids:
            blocks.setdefault(module_of(aid), []).append(aid)
        modules, slots = {}, []
        for mid, members in blocks.items():
            first = members[0]
            space = action_spaces[first]
            if not (isinstance(space, gym.spaces.Box) and space.is_bounded()
                    and np.issubdtype(space.dtype, np.floating)):
                fail("sampler", "fast", f"'rllib' for the action space {space} of {first!r} "
                                        "(the fast sampler acts in bounded float boxes)")
            for aid in members:
                if (observation_spaces[aid] != observation_spaces[first]
                        or action_spaces[aid] != action_spaces[first]):
                    fail("sampler", "fast", f"'rllib': agents {first!r} and {aid!r} of module "
                                            f"{mid!r} have different spaces")
            modules[mid] = ModuleRows(mid, tuple(members), observation_spaces[first],
                                      action_spaces[first])
        for aid in agent_ids:
            mid = module_of(aid)
            slots.append((aid, mid, modules[mid].agent_ids.index(aid)))
        return cls(tuple(agent_ids), modules, tuple(slots))
