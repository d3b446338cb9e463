"""Env API tests: official PettingZoo/RLlib checkers, adapter semantics, spaces, options."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from rl_scan.envs.core import ScanCore
from rl_scan.envs.heuristics import GreedyTeam
from rl_scan.envs.parallel_env import ScanParallelEnv
from rl_scan.envs.rllib_env import ScanMultiAgentEnv

ONE_BOX = str(Path(__file__).parent / "data" / "one_box.yaml")


def test_pettingzoo_parallel_api_test():
    parallel_api_test(ScanParallelEnv({"max_steps": 60}), num_cycles=100)


def test_pettingzoo_parallel_seed_test():
    parallel_seed_test(lambda: ScanParallelEnv({"max_steps": 60}), num_cycles=50)


def test_rllib_check_multiagent_environments():
    from ray.rllib.utils.pre_checks.env import check_multiagent_environments

    check_multiagent_environments(ScanMultiAgentEnv({"max_steps": 60}))


def test_rllib_env_runner_samples_both_policy_groups():
    """RLlib's own MultiAgentEnvRunner steps the env with one module per robot kind."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner

    from rl_scan.envs.observations import kind_of

    config = (PPOConfig()
              .environment(ScanMultiAgentEnv, env_config={"max_steps": 25})
              .env_runners(num_env_runners=0)
              .multi_agent(policies={"wheeled", "quad"},
                           policy_mapping_fn=lambda aid, *a, **k: kind_of(aid)))
    runner = MultiAgentEnvRunner(config=config)
    episodes = runner.sample(num_timesteps=60, random_actions=False)
    assert sum(e.env_steps() for e in episodes) >= 60
    modules = {sa.module_id for e in episodes for sa in e.agent_episodes.values()}
    assert modules == {"wheeled", "quad"}
    assert any(e.is_done for e in episodes)  # 25-step episodes end inside 60 steps


@pytest.mark.parametrize("scheme,team,wheeled_dim,quad_dim", [
    # rays 216*6 = 1296; own 8 (wheeled) / 9 (quad); object info 6 slots * 5 = 30 (wheeled,
    # only if the team has quads); per teammate 3 (position) + 3 (velocity) when switched on.
    (1, (2, 2), 1296 + 8 + 6 + 30, 1296 + 9 + 2 * 6),
    (3, (2, 2), 1296 + 8 + 30, 1296 + 9),
    (7, (2, 2), 1296 + 8 + 6 + 2 * 6 + 30, 1296 + 9 + 2 * 6 + 6),
    (6, (1, 3), 1296 + 8 + 3 * 6 + 30, 1296 + 9 + 3 + 2 * 6),
    (1, (0, 4), None, 1296 + 9),
    (1, (4, 0), 1296 + 8 + 3 * 6, None),
])
def test_observation_sizes_by_hand(scheme, team, wheeled_dim, quad_dim):
    env = ScanMultiAgentEnv({"comm_scheme": scheme,
                             "team": {"wheeled": team[0], "quad": team[1]}})
    assert env.possible_agents == ([f"wheeled_{i}" for i in range(team[0])]
                                   + [f"quad_{i}" for i in range(team[1])])
    for aid, space in env.observation_spaces.items():
        expected = wheeled_dim if aid.startswith("wheeled") else quad_dim
        assert space.shape == (expected,)
        assert env.action_spaces[aid].shape == ((3,) if aid.startswith("wheeled") else (5,))
    obs, _ = env.reset(seed=1)
    assert all(env.observation_spaces[a].contains(o) for a, o in obs.items())


def test_comm_block_carries_teammate_state_and_object_info():
    """Scheme 1: wheeled_0 sees wheeled_1's relative position; object info after quads look."""
    core = ScanCore({"comm_scheme": 1})
    obs = core.reset(seed=0)
    w = core.world
    comm = 1296 + 8
    rel = (w.pos[1] - w.pos[0]) / w.grid.extent
    np.testing.assert_allclose(obs["wheeled_0"][comm:comm + 3], rel, atol=1e-6)
    team = GreedyTeam(core)
    for _ in range(60):
        obs, *_ = core.step(team.act())
        if w.obj_seen_by_quad.any():
            break
    assert w.obj_seen_by_quad.any(), "quads should see an object within 60 greedy steps"
    slot0 = obs["wheeled_0"][comm + 6:comm + 11]
    assert slot0[4] == 1.0  # presence flag of the nearest object seen by a quad
    seen = np.flatnonzero(w.obj_seen_by_quad)
    d = np.hypot(*(w.obj_centre[seen, :2] - w.pos[0, :2]).T)
    nearest = seen[np.argmin(d)]
    np.testing.assert_allclose(slot0[:2], (w.obj_centre[nearest, :2] - w.pos[0, :2])
                               / w.grid.extent[:2], atol=1e-6)
    assert slot0[3] == pytest.approx(w.obj_left[nearest] / w.obj_total[nearest], abs=1e-6)


def test_both_adapters_agree_step_by_step():
    rl, pz = ScanMultiAgentEnv({"max_steps": 30}), ScanParallelEnv({"max_steps": 30})
    o1, _ = rl.reset(seed=7)
    o2, _ = pz.reset(seed=7)
    rng = np.random.default_rng(0)
    for _ in range(30):
        for a in o1:
            np.testing.assert_array_equal(o1[a], o2[a])
        acts = {a: rng.uniform(-1, 1, rl.action_spaces[a].shape) for a in rl.possible_agents}
        o1, r1, t1, tr1, _ = rl.step(acts)
        o2, r2, t2, tr2, _ = pz.step(acts)
        assert r1 == r2
    assert tr1["__all__"] and all(tr2.values()) and not t1["__all__"]
    assert rl.agents == [] and pz.agents == []


def test_reset_option_and_set_task_switch_scenario():
    env = ScanMultiAgentEnv({})
    env.reset(seed=0)
    assert env.core.world.n_cells == 720
    env.reset(seed=0, options={"scenario": "test:2"})
    assert env.core.world.scenario.name == "test:2"
    env.set_task("train:3")
    env.reset(seed=0)
    assert env.core.world.scenario.name == "train:3"
    env.reset(seed=0, options={"unrelated": 1})  # other options are ignored (gymnasium)
    assert env.core.world.scenario.name == "train:3"


def test_random_scenario_draws_a_new_scene_per_reset_deterministically():
    a, b = ScanCore({"scenario": "random"}), ScanCore({"scenario": "random"})
    a.reset(seed=3)
    b.reset(seed=3)
    assert a.world.scenario.objects == b.world.scenario.objects
    layouts = set()
    for s in range(4):
        a.reset(seed=100 + s)
        layouts.add(a.world.scenario.objects)
    assert len(layouts) == 4


def test_train_star_picks_a_train_scene_per_reset_from_the_cache():
    core = ScanCore({"scenario": "train:*"})
    names = set()
    for s in range(6):
        core.reset(seed=s)
        names.add(core.world.scenario.name)
    assert len(names) >= 4 and all(n.startswith("train:") and n != "train:*" for n in names)
    core.reset(seed=2)
    again = core.world.scenario.name
    core.reset(seed=2)
    assert core.world.scenario.name == again  # seeded


def test_termination_when_every_cell_is_scanned():
    core = ScanCore({"scenario": ONE_BOX, "max_steps": 300})
    core.reset(seed=0)
    assert core.world.n_cells == 20
    team = GreedyTeam(core)
    while True:
        _, rew, term, trunc, infos = core.step(team.act())
        if term or trunc:
            break
    assert term and not trunc and core.t < 300
    m = infos["quad_0"]["episode_metrics"]
    assert m["coverage"] == 1.0 and m["success"] == 1.0 and m["cells_scanned"] == 20
    with pytest.raises(RuntimeError, match="reset"):
        core.step(team.act())


def test_team_reward_mode_gives_everyone_the_sum():
    ind = ScanCore({"scenario": ONE_BOX, "reward_mode": "individual"})
    team = ScanCore({"scenario": ONE_BOX, "reward_mode": "team"})
    ind.reset(seed=0)
    team.reset(seed=0)
    greedy = GreedyTeam(ind)
    done, total_scanned = False, 0.0
    while not done:
        acts = greedy.act()
        _, r_ind, term, trunc, _ = ind.step(acts)
        _, r_team, *_ = team.step(acts)
        total = sum(r_ind.values())
        total_scanned += total
        assert all(v == pytest.approx(total) for v in r_team.values())
        done = term or trunc
    assert total_scanned > 0


@pytest.mark.parametrize("make", [lambda: ScanMultiAgentEnv({"render_mode": "rgb_array"}),
                                  lambda: ScanParallelEnv(render_mode="rgb_array")])
def test_render_rgb_array(make):
    env = make()
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.shape[0] > 400 and frame.shape[1] == 40 * 12
    # object columns are drawn green (nothing scanned at reset)
    assert (np.all(frame == [60, 170, 75], axis=2)).sum() > 1000


def test_bad_render_mode_and_bad_actions_fail_clearly():
    with pytest.raises(ValueError, match="render_mode='human'"):
        ScanMultiAgentEnv({"render_mode": "human"})
    env = ScanMultiAgentEnv({})
    env.reset(seed=0)
    good = {a: np.zeros(sp.shape) for a, sp in env.action_spaces.items()}
    with pytest.raises(ValueError, match=r"quad_1.*shape \(3,\).*expected \(5,\)"):
        env.step({**good, "quad_1": np.zeros(3)})
    with pytest.raises(ValueError, match="wheeled_0.*not finite"):
        env.step({**good, "wheeled_0": np.array([0.0, np.nan, 0.0])})
    with pytest.raises(ValueError, match="unknown agent 'quad_9'"):
        env.step({**good, "quad_9": np.zeros(5)})
