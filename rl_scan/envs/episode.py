"""Play one episode with any team (scripted or trained): the rollout loop of every command
that evaluates, renders or replays outside RLlib."""

from __future__ import annotations

from rl_scan.envs.core import ScanCore


def run_episode(core: ScanCore, team, seed: int = 0, scenario: str | None = None,
                frames: list | None = None, frame_every: int = 1) -> dict[str, float]:
    """Play one episode with a team (anything with ``act(obs) -> actions``); return metrics."""
    obs = core.reset(seed=seed, options={"scenario": scenario} if scenario else None)
    if frames is not None:
        frames.append(core.render_rgb())
    while True:
        obs, _, term, trunc, infos = core.step(team.act(obs))
        if frames is not None and (core.t % frame_every == 0 or term or trunc):
            frames.append(core.render_rgb())
        if term or trunc:
            return infos[core.agent_ids[0]]["episode_metrics"]
