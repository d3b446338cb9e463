"""Robot kinds: the paper's motion limits, body size and raycast sensor fans.

Actions are in [-1, 1] per dimension and scaled by these limits:
wheeled = (forward, left, yaw rate); quad = (forward, left, yaw rate, up, pitch rate).
Inside the simulator every robot gets this ``ACTION_WIDTH``-vector (wheeled: the first 3;
up = pitch = 0). Body frame: x forward, y left, z up; pitch > 0 tilts the nose (and the
sensor fan) up. ``Team`` holds the kinds' limits as tables the kernels index by kind.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from rl_scan.config import check_range, fail

KINDS = ("wheeled", "quad")
WHEELED, QUAD = 0, 1  # kind ids: positions in KINDS and rows of the Team tables
FORWARD, LEFT, YAW, UP, PITCH = range(5)  # columns of the simulator's action matrix
ACTION_WIDTH = PITCH + 1
ACTION_DIMS = {"wheeled": YAW + 1, "quad": ACTION_WIDTH}  # each kind's action is a prefix


@dataclass(frozen=True)
class RobotSpec:
    """Limits and sensor of one robot kind (paper values where the paper gives them)."""

    max_speed: float
    """Forward/back and left/right speed limit, m/s (paper: 0.2 wheeled, 0.1 quad)."""
    max_vertical_speed: float
    """Up/down speed limit, m/s (paper: 0.1 quad; 0 wheeled)."""
    max_yaw_rate: float = 3.0
    """Yaw rate limit, rad/s (paper: 3)."""
    max_pitch_rate: float = 0.0
    """Pitch rate limit, rad/s (paper: 3 quad; 0 wheeled)."""
    pitch_limits: tuple[float, float] = (0.0, 0.0)
    """Lowest and highest pitch, degrees (assumed: -60..30 for quads)."""
    radius: float = 0.25
    """Collision sphere radius, metres (assumed)."""
    altitude: float = 0.3
    """Body/sensor height: fixed for wheeled robots, the start height for quads (assumed)."""
    sensor_range: float = 2.0
    """Ray length, metres (paper: 2 wheeled, 3.5 quad)."""
    elevations: tuple[float, ...] = (0.0, 20.0, 40.0)
    """Fan elevations relative to the body, degrees (assumed)."""
    azimuth_step: float = 5.0
    """Angle between neighbouring rays of a fan, degrees (paper: 5); fans cover 360 degrees."""

    def validate(self, prefix: str = "") -> None:
        check_range(prefix + "max_speed", self.max_speed, 0.0, None, lo_open=True)
        check_range(prefix + "max_vertical_speed", self.max_vertical_speed, 0.0)
        check_range(prefix + "max_yaw_rate", self.max_yaw_rate, 0.0)
        check_range(prefix + "max_pitch_rate", self.max_pitch_rate, 0.0)
        lo, hi = self.pitch_limits
        check_range(prefix + "pitch_limits[0]", lo, -90.0, 0.0)
        check_range(prefix + "pitch_limits[1]", hi, 0.0, 90.0)
        check_range(prefix + "radius", self.radius, 0.05, 1.0)
        check_range(prefix + "altitude", self.altitude, self.radius)
        check_range(prefix + "sensor_range", self.sensor_range, 0.0, 50.0, lo_open=True)
        if not self.elevations:
            fail(prefix + "elevations", self.elevations, "at least one elevation")
        for i, e in enumerate(self.elevations):
            check_range(f"{prefix}elevations[{i}]", e, -90.0, 90.0)
        check_range(prefix + "azimuth_step", self.azimuth_step, 1.0, 180.0)
        if abs(360.0 / self.azimuth_step - round(360.0 / self.azimuth_step)) > 1e-9:
            fail(prefix + "azimuth_step", self.azimuth_step, "a divisor of 360 degrees")

    @property
    def n_rays(self) -> int:
        return len(self.elevations) * int(round(360.0 / self.azimuth_step))

    def ray_directions(self) -> np.ndarray:
        """Unit ray directions in the body frame, elevation-major, azimuth 0 = forward."""
        az = np.radians(np.arange(int(round(360.0 / self.azimuth_step))) * self.azimuth_step)
        dirs = []
        for e in np.radians(self.elevations):
            dirs.append(np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az),
                                  np.full_like(az, np.sin(e))], axis=1))
        return np.concatenate(dirs).astype(np.float64)


def default_wheeled() -> RobotSpec:
    return RobotSpec(max_speed=0.2, max_vertical_speed=0.0, max_yaw_rate=3.0,
                     max_pitch_rate=0.0, pitch_limits=(0.0, 0.0), radius=0.25, altitude=0.3,
                     sensor_range=2.0, elevations=(0.0, 20.0, 40.0))


def default_quad() -> RobotSpec:
    return RobotSpec(max_speed=0.1, max_vertical_speed=0.1, max_yaw_rate=3.0,
                     max_pitch_rate=3.0, pitch_limits=(-60.0, 30.0), radius=0.25, altitude=1.5,
                     sensor_range=3.5, elevations=(-30.0, 0.0, 30.0))


class Team(NamedTuple):
    """The robots' fixed parameters: per-robot arrays, and per-kind tables indexed by kind."""

    kind: np.ndarray
    """(n,) int64 kind id (WHEELED or QUAD) of each robot."""
    radius: np.ndarray
    """(n,) collision sphere radius of each robot, metres."""
    max_speed: np.ndarray
    """(kinds,) forward/left speed limit, m/s; also the observation's velocity scale."""
    max_vertical_speed: np.ndarray
    """(kinds,) up/down speed limit, m/s (0: the kind cannot climb)."""
    max_yaw_rate: np.ndarray
    """(kinds,) rad/s."""
    max_pitch_rate: np.ndarray
    """(kinds,) rad/s."""
    pitch_lo: np.ndarray
    """(kinds,) lowest pitch, radians."""
    pitch_hi: np.ndarray
    """(kinds,) highest pitch, radians."""
    sensor_range: np.ndarray
    """(kinds,) ray length, metres."""
    n_rays: np.ndarray
    """(kinds,) int64 rays in the kind's fan."""
    ray_dirs: np.ndarray
    """(kinds, max rays, 3) body-frame unit ray directions; rows past n_rays are 0."""


def build_team(specs: Sequence[RobotSpec], kind: np.ndarray) -> Team:
    """The Team of robots of the given kind ids, from one RobotSpec per kind (KINDS order)."""

    def table(values) -> np.ndarray:
        return np.array(list(values), dtype=np.float64)

    ray_dirs = np.zeros((len(specs), max(s.n_rays for s in specs), 3))
    for k, s in enumerate(specs):
        ray_dirs[k, :s.n_rays] = s.ray_directions()
    return Team(kind=kind, radius=table(specs[k].radius for k in kind),
                max_speed=table(s.max_speed for s in specs),
                max_vertical_speed=table(s.max_vertical_speed for s in specs),
                max_yaw_rate=table(s.max_yaw_rate for s in specs),
                max_pitch_rate=table(s.max_pitch_rate for s in specs),
                pitch_lo=table(np.radians(s.pitch_limits[0]) for s in specs),
                pitch_hi=table(np.radians(s.pitch_limits[1]) for s in specs),
                sensor_range=table(s.sensor_range for s in specs),
                n_rays=np.array([s.n_rays for s in specs], dtype=np.int64), ray_dirs=ray_dirs)
