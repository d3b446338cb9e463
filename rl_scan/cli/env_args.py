"""Command-line options that describe an environment, shared by every ``rl-scan`` command."""

from __future__ import annotations

import argparse
from typing import Any

from rl_scan.config import ConfigError, deep_merge, load_yaml, parse_yaml
from rl_scan.envs.sim.env_config import EnvConfig, make_env_config

TEAM_NAMES = {"hetero": (2, 2), "quads": (0, 4), "wheeled": (4, 0)}


def parse_team(text: str) -> dict[str, int]:
    """'2,2' (wheeled,quads) or a name: hetero (2,2), quads (0,4), wheeled (4,0)."""
    if text in TEAM_NAMES:
        w, q = TEAM_NAMES[text]
        return {"wheeled": w, "quad": q}
    try:
        w, q = (int(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"team={text!r} is invalid: allowed 'W,Q' (e.g. 2,2) or one of "
                          f"{sorted(TEAM_NAMES)}") from None
    return {"wheeled": w, "quad": q}


def parse_set(items: list[str], flag: str = "--set", example: str = "max_steps=300"
              ) -> dict[str, Any]:
    """['quad.sensor_range=3.0', 'dt=1'] -> nested mapping with YAML-typed values."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"{flag} {item!r} is invalid: allowed KEY=VALUE, e.g. {example}")
        key, value = item.split("=", 1)
        node = out
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = parse_yaml(value)
    return out


def add_env_args(parser: argparse.ArgumentParser, scenario: str | None = "ablation") -> None:
    """Add --scenario/--team/--comm/--config/--set to a sub-command."""
    g = parser.add_argument_group("environment")
    if scenario is not None:
        g.add_argument("--scenario", default=None,
                       help="ablation | train:N (0-999) | test:N (0-4) | random | a scenario "
                            f".yaml (default: {scenario})")
    g.add_argument("--team", default=None,
                   help="team as W,Q (wheeled,quads) or hetero|quads|wheeled (default 2,2)")
    g.add_argument("--comm", type=int, default=None, metavar="1-7",
                   help="communication scheme of the paper's Table II (default 1)")
    g.add_argument("--no-object-info", action="store_true",
                   help="switch off the quad->wheeled object-information channel")
    g.add_argument("--config", default=None, metavar="YAML",
                   help="an env config YAML (EnvConfig fields); flags override it")
    g.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any EnvConfig field, dotted for nested ones "
                        "(e.g. --set max_steps=300 --set quad.sensor_range=3)")


def env_config_from_args(args: argparse.Namespace) -> EnvConfig:
    """Resolve the environment flags into a validated EnvConfig."""
    return make_env_config(env_mapping_from_args(args))


def env_mapping_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Only the EnvConfig fields the user set (so presets can fill in the rest)."""
    mapping: dict[str, Any] = load_yaml(args.config) if args.config else {}
    if getattr(args, "scenario", None):
        mapping["scenario"] = args.scenario
    if args.team:
        mapping["team"] = parse_team(args.team)
    if args.comm is not None:
        mapping["comm_scheme"] = args.comm
    if args.no_object_info:
        mapping["object_info"] = False
    return deep_merge(mapping, parse_set(args.set))
