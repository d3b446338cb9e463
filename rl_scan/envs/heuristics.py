"""Scripted teams: a greedy coverage team (the reference line in every report) and random.

Greedy team, per robot and step:
1. Knowledge: the unscanned cells of every object any robot's ray has touched so far
   (the team's shared map; the same objects the object-information channel reports).
2. Target: keep the current target cell until it is scanned (or given up after
   ``patience`` steps); otherwise take the nearest known unscanned cell this kind can
   scan (wheeled: side cells below ``wheeled_reach`` m; quads: the rest first, then
   any), not within ``spread`` m of a teammate's target. Nothing known: visit the
   nearest unvisited waypoint of a 3 x 3 tour of the arena.
3. Motion: fly/drive at full speed to the target's viewpoint (outside the face, along its
   normal; above top cells), facing and pitching towards the cell (touring quads pitch
   down: ``TOUR_PITCH``). A move that would
   collide is replaced by the first free heading rotated away from it (a bug-style
   sidestep with a per-robot turning side that flips when stuck). Quads cross objects
   above their tops.
It reads the world's state directly: it is a privileged reference, not a learner.
"""

from __future__ import annotations

import math

import numpy as np

from rl_scan.envs.core import ScanCore
from rl_scan.envs.sim.dynamics import COLLIDE_NONE, SUBSTEP_RADII, collision_at
from rl_scan.envs.sim.robots import QUAD, WHEELED

TURNS = np.radians([0, 30, 60, 90, 120, 150, 180])
TOUR_PITCH = math.radians(-45.0)  # a touring quad's pitch: at cruise height a level fan
# (-30..30 degrees, 3.5 m) reaches no lower than ~1.7 m below it and misses low objects


class GreedyTeam:
    """The scripted greedy coverage team (see module doc)."""

    def __init__(self, core: ScanCore, wheeled_reach: float = 1.0, standoff: float = 0.9,
                 quad_standoff: float = 1.5, spread: float = 1.5, patience: int = 120):
        self.core = core
        self.wheeled_reach, self.standoff = wheeled_reach, standoff
        self.quad_standoff = quad_standoff
        self.spread, self.patience = spread, patience
        self._world = None

    # --------------------------------------------------------------- planning data
    def _prepare(self) -> None:
        w = self._world = self.core.world
        cells = w.cells
        normal = np.zeros((len(cells), 3))
        normal[np.arange(len(cells)), cells.face // 2] = np.where(cells.face % 2 == 1, 1.0, -1.0)
        side = cells.face < 4
        cfg = self.core.config
        self.wheeled_ok = side & (cells.centre[:, 2] < self.wheeled_reach)
        vp_w = cells.centre + normal * self.standoff
        vp_w[:, 2] = cfg.wheeled.altitude
        vp_q = cells.centre + normal * self.quad_standoff
        vp_q[~side] = cells.centre[~side] + np.array([0.0, 0.0, 1.5])
        vp_q[:, 2] = np.clip(vp_q[:, 2], cfg.quad.radius + 0.3,
                             w.grid.extent[2] - cfg.quad.radius - 0.1)
        self.viewpoint = {WHEELED: vp_w, QUAD: vp_q}
        self.cruise = float(w.obj_top.max() + 0.8) if w.n_objects else 2.0
        ext = w.grid.extent
        self.waypoints = np.array([[ext[0] * fx, ext[1] * fy] for fx in (0.25, 0.5, 0.75)
                                   for fy in (0.25, 0.5, 0.75)])
        n = w.n_robots
        self.visited = np.zeros(len(self.waypoints), dtype=bool)
        self.target = np.full(n, -1)
        self.target_age = np.zeros(n, dtype=np.int64)
        self.side = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
        self.blocked = np.zeros(n, dtype=np.int64)
        self.banned = [set() for _ in range(n)]

    # ------------------------------------------------------------------- policy
    def act(self, obs: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """Actions for every agent for the current state (reads the world, not ``obs``)."""
        if self._world is not self.core.world or self.core.t == 0:
            self._prepare()
        w = self._world
        actions = {}
        for i, aid in enumerate(w.agent_ids):
            goal, look = self._goal(i)
            actions[aid] = self._control(i, goal, look)
        return actions

    def _goal(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        w = self._world
        kind = int(w.kind[i])
        t = self.target[i]
        if t >= 0 and (w.cell_state[t] or self.target_age[i] > self.patience):
            if not w.cell_state[t]:
                self.banned[i].add(int(t))
            t = self.target[i] = -1
        if t < 0:
            t = self.target[i] = self._pick(i, kind)
            self.target_age[i] = 0
        self.target_age[i] += 1
        if t >= 0:
            return self.viewpoint[kind][t], w.cells.centre[t]
        pos = w.pos[i, :2]
        for k, p in enumerate(self.waypoints):
            if np.linalg.norm(p - pos) < 1.5:
                self.visited[k] = True
        free = np.flatnonzero(~self.visited)
        if len(free) == 0:
            self.visited[:] = False
            free = np.arange(len(self.waypoints))
        p = self.waypoints[free[np.argmin(np.linalg.norm(self.waypoints[free] - pos, axis=1))]]
        z = w.pos[i, 2] if kind == WHEELED else self.cruise
        return np.array([p[0], p[1], z]), None

    def _pick(self, i: int, kind: int) -> int:
        w = self._world
        known = (w.cell_state == 0) & (w.obj_seen[w.cells.obj] > 0)
        if self.banned[i]:
            known[list(self.banned[i])] = False
        if kind == QUAD:
            pool = known & ~self.wheeled_ok
            if not pool.any() or w.config.team.wheeled == 0:
                pool = known
        else:
            pool = known & self.wheeled_ok
        others = [self.target[j] for j in range(w.n_robots) if j != i and self.target[j] >= 0]
        cand = np.flatnonzero(pool)
        if len(cand) == 0:
            return -1
        if others:
            d_other = np.linalg.norm(w.cells.centre[cand][:, None] - w.cells.centre[others][None],
                                     axis=2).min(axis=1)
            spread_ok = d_other > self.spread
            if spread_ok.any():
                cand = cand[spread_ok]
        d = np.linalg.norm(self.viewpoint[kind][cand] - w.pos[i], axis=1)
        return int(cand[np.argmin(d)])

    def _control(self, i: int, goal: np.ndarray, look: np.ndarray | None) -> np.ndarray:
        w, cfg = self._world, self.core.config
        quad = w.kind[i] == QUAD
        spec = cfg.quad if quad else cfg.wheeled
        dt = cfg.dt
        pos = w.pos[i]
        delta = goal - pos
        dist_xy = float(np.hypot(delta[0], delta[1]))
        if quad and dist_xy > 2.5 and self._path_blocked(pos, goal):
            delta[2] = self.cruise - pos[2]  # climb over objects when far away
        # Heading: towards the looked-at cell, else along the motion.
        ref = look if look is not None else goal
        want_yaw = math.atan2(ref[1] - pos[1], ref[0] - pos[0])
        if dist_xy < 1e-6 and look is None:
            want_yaw = w.yaw[i]
        dyaw = math.atan2(math.sin(want_yaw - w.yaw[i]), math.cos(want_yaw - w.yaw[i]))
        a_yaw = float(np.clip(dyaw / (spec.max_yaw_rate * dt), -1, 1))
        new_yaw = w.yaw[i] + a_yaw * spec.max_yaw_rate * dt
        a_up = a_pitch = 0.0
        if quad:
            a_up = float(np.clip(delta[2] / (spec.max_vertical_speed * dt), -1, 1))
            if look is not None:
                horiz = max(math.hypot(look[0] - pos[0], look[1] - pos[1]), 1e-6)
                want_pitch = math.atan2(look[2] - pos[2], horiz)
                lo, hi = np.radians(spec.pitch_limits)
                want_pitch = float(np.clip(want_pitch, lo, hi))
            else:  # touring above the objects: look down, or the fan sees nothing below it
                want_pitch = float(np.clip(TOUR_PITCH, *np.radians(spec.pitch_limits)))
            a_pitch = float(np.clip((want_pitch - w.pitch[i]) / (spec.max_pitch_rate * dt),
                                    -1, 1))
        step = min(dist_xy, spec.max_speed * dt)
        move, vz, turned = self._free_move(i, math.atan2(delta[1], delta[0]), step,
                                           a_up * spec.max_vertical_speed * dt)
        a_up = vz / (spec.max_vertical_speed * dt) if quad else 0.0
        self.blocked[i] = self.blocked[i] + 1 if turned else max(0, self.blocked[i] - 1)
        if self.blocked[i] > 25:
            self.side[i] *= -1
            self.blocked[i] = 0
        c, s = math.cos(new_yaw), math.sin(new_yaw)
        fwd = (move[0] * c + move[1] * s) / (spec.max_speed * dt)
        left = (-move[0] * s + move[1] * c) / (spec.max_speed * dt)
        act = [np.clip(fwd, -1, 1), np.clip(left, -1, 1), a_yaw]
        if quad:
            act = [act[0], act[1], a_yaw, a_up, a_pitch]
        return np.array(act, dtype=np.float32)

    def _free_move(self, i: int, heading: float, step: float,
                   vz: float) -> tuple[np.ndarray, float, bool]:
        """The first collision-free (horizontal move, vertical move); turned = not straight."""
        if step > 1e-6:
            for dz in (vz, 0.0) if vz else (0.0,):
                for turn in self._turn_order(i):
                    h = heading + turn
                    cand = np.array([math.cos(h), math.sin(h)]) * step
                    if self._free(i, cand, dz):
                        return cand, dz, turn != 0.0
        if vz and self._free(i, np.zeros(2), vz):
            return np.zeros(2), vz, step > 1e-6
        return np.zeros(2), 0.0, step > 1e-6

    def _turn_order(self, i: int) -> np.ndarray:
        s = self.side[i]
        return np.concatenate([[0.0], s * TURNS[1:], -s * TURNS[1:-1]])

    def _free(self, i: int, move_xy: np.ndarray, dz: float) -> bool:
        w = self._world
        g = w.grid
        pos = w.pos[i]
        length = math.sqrt(move_xy @ move_xy + dz * dz)
        n_sub = max(1, int(math.ceil(length / (SUBSTEP_RADII * w.radius[i]))))
        for k in range(1, n_sub + 1):
            f = k / n_sub
            p = pos + f * np.array([move_xy[0], move_xy[1], dz])
            if collision_at(w.occ, g.nx, g.ny, g.nz, g.cell_size, w.pos, w.radius, i,
                            p[0], p[1], p[2]) != COLLIDE_NONE:
                return False
        return True

    def _path_blocked(self, pos: np.ndarray, goal: np.ndarray) -> bool:
        """True if the straight horizontal segment at the current height meets an object."""
        w = self._world
        g = w.grid
        n = int(np.hypot(*(goal[:2] - pos[:2])) / (0.5 * g.cell_size)) + 1
        pts = pos[:2] + np.linspace(0, 1, n)[:, None] * (goal[:2] - pos[:2])
        idx = np.clip((pts / g.cell_size).astype(int), 0, [g.nx - 1, g.ny - 1])
        k = min(int(pos[2] / g.cell_size), g.nz - 1)
        return bool(np.any(w.object_id[idx[:, 0], idx[:, 1], : k + 1] >= 0))


class RandomTeam:
    """Uniform random actions from the env's action spaces (a lower reference line)."""

    def __init__(self, core: ScanCore, seed: int = 0):
        self.core = core
        self.rng = np.random.default_rng(seed)

    def act(self, obs: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        return {aid: self.rng.uniform(-1, 1, sp.shape).astype(np.float32)
                for aid, sp in self.core.action_spaces.items()}
