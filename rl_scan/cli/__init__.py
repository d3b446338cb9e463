"""The ``rl-scan`` command line, the top floor: ``parser.py`` reads the arguments,
``commands.py`` does the work, ``env_args.py`` turns flags into an env config and the
``bench_*.py`` modules are the benchmarks.

  rl-scan scenario show|export      a scenario's objects, cells and starts / YAML or mesh
  rl-scan bench env|train|mpe       simulator speed, training speed, MPE external check
  rl-scan train                     train POCA or PPO through Ray Tune
  rl-scan meta-train / adapt        MetaPOCA; adapt (fine-tune) a checkpoint to a scene
  rl-scan experiment meta-mrss      the paper's protocol on held-out scenes
  rl-scan ablate comm|algo|team|hpo Tune + Optuna studies
  rl-scan evaluate / render / replay  metrics table, GIF/PNG, interactive 3D replay
  rl-scan report RESULTS_DIR        Markdown + HTML report with figures and statistics

Errors in the input (unknown keys, bad values, missing files) print one line naming the
field and exit with status 2 before anything runs.
"""

from __future__ import annotations

import sys

from rl_scan.config import ConfigError, RunInterrupted


def main(argv: list[str] | None = None) -> int:
    from rl_scan.cli.parser import build_parser

    parser = build_parser()
    args = parser.parse_args(argv)
    ray_was_up = _ray_is_up()
    if not args.verbose and args.command not in RAY_FREE:
        quiet_ray()
    try:
        check_outputs(args)
        return args.func(args)
    except (ConfigError, ValueError) as e:
        print(f"rl-scan {args.command}: error: {e}", file=sys.stderr)
        return 2
    except (RunInterrupted, KeyboardInterrupt) as e:
        again = ("run the same command again to continue" if args.command == "experiment"
                 else "the same command with --resume continues it")
        print(f"rl-scan {args.command}: interrupted{f': {e}' if str(e) else ''}; {again}",
              file=sys.stderr)
        return 130
    finally:
        if not ray_was_up and _ray_is_up():
            # A command that started Ray stops it, so in-process callers (notebooks, tests)
            # can start their own Ray afterwards ("ray.init twice" otherwise).
            import ray

            ray.shutdown()


RAY_FREE = ("scenario", "report")  # commands that never import Ray


def quiet_ray() -> None:
    """Keep Ray's own lines out of the console (``--verbose`` keeps them): its INFO and
    WARNING notices (token authentication, "Started a local Ray instance", "You are running
    POCA on the new API stack", Tune's result-file notes, RLlib deprecations) and Optuna's
    INFO lines (our progress lines say what they did). Errors stay.
    Ray sets its loggers' levels when imported and again in ``ray.init`` (from
    RAY_LOGGER_LEVEL), so both are set here, before either happens."""
    import logging
    import os

    os.environ.setdefault("RAY_LOGGER_LEVEL", "error")
    import ray  # noqa: F401 - configures the "ray" loggers, which are then turned down

    for name in ("ray", "ray.rllib", "ray.tune"):
        logging.getLogger(name).setLevel(logging.ERROR)
    logging.getLogger("optuna").setLevel(logging.WARNING)  # "A new study created in RDB"


def check_outputs(args) -> None:
    """Every output path of the command can be written (checked before any work)."""
    from pathlib import Path

    from rl_scan.config import check_writable

    if getattr(args, "results", None):
        check_writable("results", args.results, folder=True)
    if args.command == "report":
        out = args.out or Path(args.results_dir) / "report"
        check_writable("out", out, folder=True)
    elif getattr(args, "out", None):
        check_writable("out", args.out, folder=False)
    if getattr(args, "json", None):
        check_writable("json", args.json, folder=False)


def _ray_is_up() -> bool:
    """Whether Ray is initialised in this process, without importing Ray if nothing did."""
    ray = sys.modules.get("ray")
    return ray is not None and ray.is_initialized()

