"""The cluster examples of docs/cluster.md: the `ray up` config passes Ray's own schema
check, and the KubeRay RayJob runs a valid rl-scan command on nodes that fit its runs."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
import yaml

DOCS = Path(__file__).resolve().parent.parent / "docs" / "cluster"


def _ray_up_check(config: dict) -> None:
    """What `ray up` runs on a config before anything starts."""
    from ray.autoscaler._private.util import prepare_config, validate_config

    validate_config(prepare_config(config))


def test_the_ray_up_config_passes_rays_schema():
    config = yaml.safe_load((DOCS / "ray-up.yaml").read_text())
    _ray_up_check(config)
    assert all("RAY_AUTH_MODE=token" in c for c in
               config["head_start_ray_commands"][1:] + config["worker_start_ray_commands"][1:])
    import jsonschema

    broken = {**config, "worker_start_ray_commands": [{"ray start": "x"}]}  # a YAML slip
    with pytest.raises(jsonschema.ValidationError):
        _ray_up_check(broken)


def test_the_rayjob_runs_a_valid_paper_command_on_nodes_that_fit_it():
    from rl_scan.cli.parser import build_parser
    from rl_scan.tuning.driver import required_cpus
    from rl_scan.tuning.presets import get_preset

    job = yaml.safe_load((DOCS / "rayjob-paper.yaml").read_text())
    assert (job["apiVersion"], job["kind"]) == ("ray.io/v1", "RayJob")
    argv = shlex.split(job["spec"]["entrypoint"])
    assert argv[0] == "rl-scan"
    args = build_parser().parse_args(argv[1:])  # exits on a bad flag
    assert args.command == "experiment" and args.preset == "paper"
    per_run = required_cpus(get_preset("paper"))
    assert per_run == 3  # 1 learner CPU + 2 env runners
    cluster = job["spec"]["rayClusterSpec"]
    for group in cluster["workerGroupSpecs"]:
        cpus = int(group["rayStartParams"]["num-cpus"])
        container = group["template"]["spec"]["containers"][0]
        assert cpus % per_run == 0 and cpus >= per_run
        assert int(container["resources"]["requests"]["cpu"]) == cpus
        assert {"name": "RAY_AUTH_MODE", "value": "token"} in container["env"]
