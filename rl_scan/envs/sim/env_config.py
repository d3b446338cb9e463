"""The environment config: one frozen dataclass shared by the simulator and both adapters.

Fields the paper does not fix are marked *assumed*; their defaults were chosen so that
the scripted greedy team scans >= 95 % of the ablation scenario within ``max_steps``
(see ``rl-scan bench env``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from rl_scan.config import build_config, check_range, fail
from rl_scan.envs.sim.comms import SCHEMES
from rl_scan.envs.sim.robots import RobotSpec, default_quad, default_wheeled
from rl_scan.envs.sim.scenarios import START_SLOTS, ScenarioDistribution, parse_scenario_name


@dataclass(frozen=True)
class TeamConfig:
    """How many robots of each kind (any mix; at most 8 in all)."""

    wheeled: int = 2
    quad: int = 2

    def validate(self, prefix: str = "") -> None:
        check_range(prefix + "wheeled", self.wheeled, 0, START_SLOTS)
        check_range(prefix + "quad", self.quad, 0, START_SLOTS)
        if not 1 <= self.wheeled + self.quad <= START_SLOTS:
            fail(prefix[:-1] or "team", {"wheeled": self.wheeled, "quad": self.quad},
                 f"between 1 and {START_SLOTS} robots in all")

    @property
    def agent_ids(self) -> list[str]:
        return [f"wheeled_{i}" for i in range(self.wheeled)] + [
            f"quad_{i}" for i in range(self.quad)]


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines a scanning environment."""

    scenario: str = "ablation"
    """'ablation', 'train:N', 'test:N', 'random' (a new train-distribution draw per reset)
    or a scenario YAML path."""
    team: TeamConfig = field(default_factory=TeamConfig)
    comm_scheme: int = 1
    """Table II scheme 1..7 (paper's recommendation: 1)."""
    object_info: bool = True
    """Quadcopters send object information to wheeled robots (paper's recommendation)."""
    object_info_slots: int = 6
    """How many seen objects the object-information channel describes (assumed)."""
    reward_mode: Literal["individual", "team"] = "individual"
    """'individual': each robot gets its own scans minus its collisions; 'team': every
    robot gets the team sum (POCA's group reward)."""
    scan_reward: float = 1.0
    collision_penalty: float = 1.0
    dt: float = 2.0
    """Seconds per env step (assumed; see module doc)."""
    max_steps: int = 500
    """Episode limit in env steps (assumed; see module doc)."""
    arena: tuple[float, float, float] = (20.0, 20.0, 8.0)
    """Arena size in metres (assumed)."""
    cell_size: float = 0.5
    """Voxel edge in metres (assumed)."""
    start_jitter: float = 0.5
    """Uniform noise (metres, per axis) on start positions at each reset (assumed); 0 = fixed."""
    quad_flight_time: float = 0.0
    """Seconds a quad can fly per episode; 0 = unlimited (the default, as in the paper).
    *Assumed* (ours: the paper gives flight no cost): a quad whose time is spent lands
    where it is, holds that place and scans nothing for the rest of the episode (the
    landing manoeuvre itself is not modelled; its rays still observe)."""
    fault_at_step: int = 0
    """Testing fault tolerance: raise an error at this step of the env's life, counted over
    all its episodes (0 = never), so a fault can land after a run's first checkpoint..."""
    fault_once_file: str = ""
    """...once: the error creates this file and does not recur while it exists."""
    fault_kind: Literal["raise", "nan_reward"] = "raise"
    """What the fault is: an exception, or a NaN reward for every robot (a non-finite loss)."""
    wheeled: RobotSpec = field(default_factory=default_wheeled)
    quad: RobotSpec = field(default_factory=default_quad)
    scenario_distribution: ScenarioDistribution = field(default_factory=ScenarioDistribution)

    def validate(self, prefix: str = "") -> None:
        parse_scenario_name(self.scenario)
        if self.comm_scheme not in SCHEMES:
            fail(prefix + "comm_scheme", self.comm_scheme, f"one of {sorted(SCHEMES)}")
        check_range(prefix + "object_info_slots", self.object_info_slots, 1, 32)
        check_range(prefix + "scan_reward", self.scan_reward, 0.0)
        check_range(prefix + "collision_penalty", self.collision_penalty, 0.0)
        check_range(prefix + "dt", self.dt, 0.0, 10.0, lo_open=True)
        check_range(prefix + "max_steps", self.max_steps, 1, 1_000_000)
        check_range(prefix + "cell_size", self.cell_size, 0.05, 5.0)
        for i, (axis, lo) in enumerate(zip("xyz", (4.0, 4.0, 2.0))):
            check_range(f"{prefix}arena.{axis}", self.arena[i], lo, 200.0)
            cells = self.arena[i] / self.cell_size
            if abs(cells - round(cells)) > 1e-9:
                fail(f"{prefix}arena.{axis}", self.arena[i],
                     f"a multiple of cell_size={self.cell_size}")
        check_range(prefix + "start_jitter", self.start_jitter, 0.0, 2.0)
        check_range(prefix + "quad_flight_time", self.quad_flight_time, 0.0)
        check_range(prefix + "fault_at_step", self.fault_at_step, 0)
        if self.fault_kind not in ("raise", "nan_reward"):
            fail(prefix + "fault_kind", self.fault_kind, "'raise' or 'nan_reward'")
        if self.quad.altitude > self.arena[2] - self.quad.radius:
            fail(prefix + "quad.altitude", self.quad.altitude,
                 f"at most arena height - radius = {self.arena[2] - self.quad.radius}")


def make_env_config(overrides: dict[str, Any] | EnvConfig | None = None) -> EnvConfig:
    """Build an EnvConfig from a (possibly nested, possibly RLlib EnvContext) mapping."""
    if isinstance(overrides, EnvConfig):
        return overrides
    return build_config(EnvConfig, dict(overrides or {}))
