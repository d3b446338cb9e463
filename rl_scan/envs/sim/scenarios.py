"""Scenarios: which objects stand where and where the robots start.

Named scenarios:
  ``ablation``   the paper's ablation scene: 4 cubes of 6^3 cells (720 cells), fixed layout.
  ``train:N``    N in [0, 1000): the training set, sampled from ``ScenarioDistribution``.
  ``test:N``     N in [0, 5): five held-out scenarios from a separate seed stream.
  ``train:*``    a random training scenario per reset (domain randomisation over the set).
  a YAML path    objects and (optionally) starts listed by hand; see presets/scenarios/.
The paper's uncertainty (number and size ~ randint; shape proportions and positions ~
normal; no overlaps) is the default ``ScenarioDistribution``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from rl_scan.config import ConfigError, build_config, check_range, fail, load_yaml
from rl_scan.envs.sim.objects import ObjectSpec

N_TRAIN, N_TEST = 1000, 5
TRAIN_ENTROPY, TEST_ENTROPY = 20210928, 21091361  # separate seed streams
START_SLOTS = 8
SAMPLED_SHAPES = ("box", "cylinder", "sphere", "lshape", "hull")


@dataclass(frozen=True)
class Scenario:
    """Objects plus start positions (x, y) for up to ``START_SLOTS`` robots, in metres."""

    name: str
    objects: tuple[ObjectSpec, ...]
    starts: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class ScenarioDistribution:
    """The uncertainty the train and test scenarios are drawn from (paper Sec. III-A)."""

    n_objects: tuple[int, int] = (2, 6)
    """Inclusive range of the object count (randint)."""
    size_cells: tuple[int, int] = (3, 8)
    """Inclusive range of each horizontal extent, in cells (randint)."""
    height_cells: tuple[int, int] = (3, 8)
    """Inclusive range of the height, in cells (randint)."""
    shape_weights: tuple[float, float, float, float, float] = (0.4, 0.15, 0.1, 0.2, 0.15)
    """Probabilities of box, cylinder, sphere, lshape, hull."""
    proportion_sigma: float = 0.15
    """Std of the normal jitter of L-shape arm proportions and hull points."""
    position_sigma: float = 3.5
    """Std (metres) of object centres around the arena centre (normal)."""
    min_gap: float = 1.0
    """Minimum free gap between objects' footprints, metres."""

    def validate(self, prefix: str = "") -> None:
        for name in ("n_objects", "size_cells", "height_cells"):
            lo, hi = getattr(self, name)
            check_range(f"{prefix}{name}[0]", lo, 1)
            check_range(f"{prefix}{name}[1]", hi, lo)
        if min(self.shape_weights) < 0 or sum(self.shape_weights) <= 0:
            fail(prefix + "shape_weights", self.shape_weights, "non-negative weights, sum > 0")
        check_range(prefix + "proportion_sigma", self.proportion_sigma, 0.0, 1.0)
        check_range(prefix + "position_sigma", self.position_sigma, 0.0, None, lo_open=True)
        check_range(prefix + "min_gap", self.min_gap, 0.0)


def _yaml_scenario(path: Path) -> Scenario:
    data = load_yaml(path)
    unknown = set(data) - {"name", "objects", "starts"}
    if unknown:
        raise ConfigError(f"unknown key {sorted(unknown)[0]!r} in scenario file {str(path)!r}: "
                          "allowed keys are ['name', 'objects', 'starts']")
    objs = data.get("objects")
    if not isinstance(objs, list) or not objs:
        raise ConfigError(f"scenario file {str(path)!r}: 'objects' must be a non-empty list")
    specs = []
    for i, o in enumerate(objs):
        if not isinstance(o, dict):
            raise ConfigError(f"scenario file {str(path)!r}: objects[{i}] must be a mapping")
        o = dict(o)
        if o.get("path"):  # mesh paths are relative to the YAML file
            o["path"] = str((path.parent / o["path"]).resolve())
        specs.append(build_config(ObjectSpec, o, prefix=f"objects[{i}]."))
    starts = tuple(tuple(map(float, s)) for s in data.get("starts", []))
    for i, s in enumerate(starts):
        if len(s) != 2:
            fail(f"starts[{i}]", list(s), "an [x, y] pair in metres")
    return Scenario(name=str(data.get("name", path.stem)), objects=tuple(specs), starts=starts)


def preset_path(name: str) -> Path:
    """Path of a scenario YAML shipped with rl-scan."""
    return Path(str(resources.files("rl_scan") / "presets" / "scenarios" / f"{name}.yaml"))


def scenario_rng(name: str) -> np.random.Generator:
    """The generator that defines a named sampled scenario (train:N or test:N)."""
    kind, idx = name.split(":")
    entropy = TRAIN_ENTROPY if kind == "train" else TEST_ENTROPY
    return np.random.default_rng(np.random.SeedSequence(entropy, spawn_key=(int(idx),)))


def parse_scenario_name(name: str) -> str:
    """Validate a scenario reference; return its canonical form or raise ConfigError."""
    m = re.fullmatch(r"(train|test):(\d+)", name)
    if m:
        limit = N_TRAIN if m.group(1) == "train" else N_TEST
        if not 0 <= int(m.group(2)) < limit:
            fail("scenario", name, f"{m.group(1)}:N with 0 <= N < {limit}")
        return f"{m.group(1)}:{int(m.group(2))}"
    if name in ("ablation", "random", "train:*") or preset_path(name).is_file():
        return name
    if name.endswith((".yaml", ".yml")):
        if not Path(name).is_file():
            raise ConfigError(f"scenario file {name!r} does not exist")
        return name
    fail("scenario", name, "'ablation', 'random', 'train:N' (0<=N<1000), 'train:*', "
                           "'test:N' (0<=N<5) or a path to a scenario .yaml file")


def sample_object(rng: np.random.Generator, dist: ScenarioDistribution,
                  cell: float) -> ObjectSpec:
    """Draw one object's shape and size (position is set by the placer)."""
    w = np.asarray(dist.shape_weights, dtype=np.float64)
    shape = SAMPLED_SHAPES[rng.choice(len(SAMPLED_SHAPES), p=w / w.sum())]
    sx, sy = (int(v) for v in rng.integers(dist.size_cells[0], dist.size_cells[1] + 1, 2))
    sz = int(rng.integers(dist.height_cells[0], dist.height_cells[1] + 1))
    if shape in ("cylinder", "sphere"):
        sy = sx
    if shape == "sphere":
        sz = sx
    props = tuple(float(v) for v in np.clip(rng.normal(0.5, dist.proportion_sigma, 2), .2, .8))
    points = ()
    if shape == "hull":
        pts = np.clip(rng.normal(0.5, 0.2 + dist.proportion_sigma, (10, 3)), 0, 1)
        pts[:, 2] = np.where(np.arange(10) < 4, 0.0, pts[:, 2])  # a flat base on the floor
        points = tuple(tuple(float(c) for c in p) for p in pts)
    return ObjectSpec(shape=shape, size=(sx * cell, sy * cell, sz * cell), proportions=props,
                      points=points)


def check_fits(dist: ScenarioDistribution, extent: np.ndarray) -> None:
    """Reject distributions whose largest draw cannot fit in the arena (before sampling)."""
    side = dist.size_cells[1] * 0.5 + dist.min_gap
    need = dist.n_objects[1] * side * side
    have = 0.5 * (extent[0] - 2.0) * (extent[1] - 2.0)  # half the floor, 1 m border kept free
    if need > have:
        fail("scenario_distribution.n_objects", list(dist.n_objects),
             f"at most {int(have // (side * side))} objects of up to "
             f"{dist.size_cells[1]} cells (+{dist.min_gap} m gap) in a "
             f"{extent[0]:g} x {extent[1]:g} m arena")


def sample_scenario(name: str, rng: np.random.Generator, dist: ScenarioDistribution,
                    extent: np.ndarray, cell: float, max_tries: int = 500) -> Scenario:
    """Sample objects (no overlaps, gap >= min_gap) and robot starts inside the arena."""
    check_fits(dist, extent)
    n = int(rng.integers(dist.n_objects[0], dist.n_objects[1] + 1))
    placed: list[ObjectSpec] = []
    boxes: list[np.ndarray] = []  # footprint (xmin, ymin, xmax, ymax) of each object
    centre = extent[:2] / 2
    for _ in range(n):
        spec = sample_object(rng, dist, cell)
        half = np.array(spec.size[:2]) / 2
        for _ in range(max_tries):
            pos = rng.normal(centre, dist.position_sigma)
            pos = np.round(pos / cell) * cell + (half % cell)  # align faces with the grid
            lo, hi = pos - half, pos + half
            if np.any(lo < 1.0) or np.any(hi > extent[:2] - 1.0):
                continue
            box = np.concatenate([lo, hi])
            if all(_gap(box, b) >= dist.min_gap for b in boxes):
                break
        else:
            raise ConfigError(f"scenario {name!r}: could not place object {len(placed)} "
                              f"without overlap after {max_tries} tries; lower "
                              "scenario_distribution.n_objects or size_cells")
        boxes.append(box)
        placed.append(ObjectSpec(shape=spec.shape, size=spec.size, proportions=spec.proportions,
                                 points=spec.points, position=(float(pos[0]), float(pos[1]))))
    starts = sample_starts(rng, boxes, extent)
    return Scenario(name=name, objects=tuple(placed), starts=starts)


def _gap(a: np.ndarray, b: np.ndarray) -> float:
    dx = max(b[0] - a[2], a[0] - b[2], 0.0)
    dy = max(b[1] - a[3], a[1] - b[3], 0.0)
    return float(np.hypot(dx, dy)) if (dx > 0 or dy > 0) else -1.0


def sample_starts(rng: np.random.Generator, boxes: list[np.ndarray], extent: np.ndarray,
                  clearance: float = 1.0, spacing: float = 1.0) -> tuple:
    """Start positions near the arena border, clear of objects and of each other."""
    starts: list[np.ndarray] = []
    for _ in range(5000):
        if len(starts) == START_SLOTS:
            break
        p = rng.uniform(0.75, extent[:2] - 0.75)
        border = min(p[0], p[1], extent[0] - p[0], extent[1] - p[1])
        if border > 3.0:
            continue
        pt = np.concatenate([p, p])
        if any(_gap(pt, b) < clearance for b in boxes):
            continue
        if any(np.linalg.norm(p - s) < spacing for s in starts):
            continue
        starts.append(p)
    if len(starts) < START_SLOTS:
        raise ConfigError("could not place robot starts clear of the objects; the arena is "
                          "too crowded")
    return tuple((round(float(s[0]), 3), round(float(s[1]), 3)) for s in starts)


def load_scenario(name: str, dist: ScenarioDistribution, extent: np.ndarray, cell: float,
                  rng: np.random.Generator | None = None) -> Scenario:
    """Resolve a scenario reference (see module doc). ``random`` needs ``rng``."""
    name = parse_scenario_name(name)
    if name == "random":
        if rng is None:
            raise ValueError("scenario 'random' needs a generator")
        return sample_scenario("random", rng, dist, extent, cell)
    if ":" in name:
        return sample_scenario(name, scenario_rng(name), dist, extent, cell)
    path = preset_path(name) if preset_path(name).is_file() else Path(name)
    scenario = _yaml_scenario(path)
    if len(scenario.starts) < START_SLOTS:
        boxes = [np.array([o.position[0] - o.size[0] / 2, o.position[1] - o.size[1] / 2,
                           o.position[0] + o.size[0] / 2, o.position[1] + o.size[1] / 2])
                 for o in scenario.objects]
        extra = sample_starts(np.random.default_rng(0), boxes, extent)
        scenario = Scenario(scenario.name, scenario.objects,
                            scenario.starts + extra[len(scenario.starts):])
    return scenario
