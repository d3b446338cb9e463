"""The rl-scan command line: outputs, written files and one-line errors (exit status 2)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from rl_scan.cli import main
from rl_scan.envs.sim.env_config import EnvConfig


def run(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_scenario_show_counts_cells(capsys):
    code, out, _ = run(capsys, "scenario", "show", "ablation")
    assert code == 0
    assert "4 objects, 720 cells" in out
    assert out.count("180") >= 4 and "quad_1" in out


def test_scenario_export_yaml_round_trips(capsys, tmp_path):
    path = tmp_path / "scene.yaml"
    assert run(capsys, "scenario", "export", "train:12", str(path))[0] == 0
    _, original, _ = run(capsys, "scenario", "show", "train:12")
    _, reloaded, _ = run(capsys, "scenario", "show", str(path))
    cells = [line for line in original.splitlines() if "cells (arena" in line]
    assert cells and cells[0].split("'")[2] == [
        line for line in reloaded.splitlines() if "cells (arena" in line][0].split("'")[2]


@pytest.mark.parametrize("suffix", [".obj", ".glb", ".stl", ".ply"])
def test_scenario_export_mesh(capsys, tmp_path, suffix):
    path = tmp_path / f"scene{suffix}"
    assert run(capsys, "scenario", "export", "ablation", str(path))[0] == 0
    mesh = trimesh.load(path, force="mesh")
    np.testing.assert_allclose(mesh.bounds, [[5.0, 4.5, 0.0], [15.0, 15.0, 3.0]])


def test_render_writes_png_and_gif(capsys, tmp_path):
    png, gif = tmp_path / "last.png", tmp_path / "ep.gif"
    code, out, _ = run(capsys, "render", "--scenario", "test:2", "--out", str(png))
    assert code == 0 and "coverage" in out
    assert Image.open(png).size[0] == 480
    code, _, _ = run(capsys, "render", "--scenario", "test:2", "--set", "max_steps=40",
                     "--every", "10", "--out", str(gif))
    assert code == 0
    assert Image.open(gif).n_frames == 5  # reset frame + steps 10, 20, 30, 40


def test_bench_env_smoke_writes_figures(capsys, tmp_path):
    out_json = tmp_path / "bench.json"
    code, out, _ = run(capsys, "bench", "env", "--seconds", "0.2", "--seeds", "1", "--no-pin",
                       "--json", str(out_json))
    assert code == 0 and "raycast kernel rays/s" in out
    res = json.loads(out_json.read_text())
    for key in ("core_steps_per_s", "rllib_steps_per_s", "pettingzoo_steps_per_s",
                "kernel_rays_per_s", "peak_rss_mb"):
        assert res[key] > 0
    assert res["rays_per_step"] == 4 * 216
    assert res["greedy_ablation_coverage"] > res["random_ablation_coverage"]
    from rl_scan.envs.core import ScanCore  # the same episode played here, independently
    from rl_scan.envs.episode import run_episode
    from rl_scan.envs.heuristics import GreedyTeam

    core = ScanCore({"scenario": "ablation"})
    assert res["greedy_ablation_coverage"] == run_episode(core, GreedyTeam(core),
                                                          seed=0)["coverage"]


@pytest.mark.parametrize("argv,needle", [
    (["scenario", "show", "train:1000"], "scenario='train:1000'"),
    (["scenario", "show", "ablation", "--set", "max_step=3"], "did you mean 'max_steps'"),
    (["scenario", "show", "ablation", "--team", "2"], "team='2'"),
    (["scenario", "show", "ablation", "--comm", "9"], "comm_scheme=9"),
    (["scenario", "show", "missing.yaml"], "'missing.yaml' does not exist"),
    (["render", "--out", "x.jpg"], "out='x.jpg'"),
    (["replay", "--out", "x.png"], "allowed a path ending in .html"),
    (["bench", "env", "--seconds", "0"], "seconds=0.0"),
    (["bench", "train", "--threads", "0"], "threads=0"),
    (["bench", "train", "--batch", "0"], "batch=0"),
    (["meta-train", "--preset", "smoke", "--meta", "inner_updates=0"],
     "meta-poca.inner_updates=0 is invalid"),
    (["meta-train", "--preset", "smoke", "--meta", "tasks=1001"], "meta-poca.tasks=1001"),
    (["meta-train", "--preset", "smoke", "--meta", "query_steps=99"],
     "meta-poca.query_steps=99 is invalid: allowed a multiple of num_envs_per_env_runner=2"),
    (["meta-train", "--preset", "smoke", "--meta", "support_steps=200"],
     "total_env_steps=800 is invalid: allowed a multiple of 600, MetaPOCA's env steps"),
    (["meta-train", "--preset", "smoke", "--meta", "outer"], "--meta 'outer' is invalid"),
])
def test_bad_input_is_one_clear_line(capsys, argv, needle):
    code, out, err = run(capsys, *argv)
    assert code == 2 and out == ""
    assert needle in err and len(err.strip().splitlines()) == 1


def test_an_env_config_yaml_sets_fields_and_flags_override_it(tmp_path, capsys):
    from rl_scan.cli.env_args import env_config_from_args
    from rl_scan.cli.parser import build_parser

    path = tmp_path / "env.yaml"
    path.write_text("scenario: 'test:1'\nmax_steps: 77\nteam: {wheeled: 1, quad: 3}\n"
                    "quad: {sensor_range: 3.0}\n")
    env = env_config_from_args(build_parser().parse_args(["train", "--config", str(path)]))
    assert (env.scenario, env.max_steps, env.team.wheeled, env.team.quad,
            env.quad.sensor_range) == ("test:1", 77, 1, 3, 3.0)
    assert env.quad.max_speed == EnvConfig().quad.max_speed  # partial nested: rest kept
    env = env_config_from_args(build_parser().parse_args(
        ["train", "--config", str(path), "--team", "2,2", "--set", "max_steps=5"]))
    assert (env.scenario, env.max_steps, env.team.wheeled, env.quad.sensor_range) == (
        "test:1", 5, 2, 3.0)
    path.write_text("max_stepz: 5\n")
    code, _, err = run(capsys, "scenario", "show", "ablation", "--config", str(path))
    assert code == 2 and "max_stepz" in err


def test_exponent_numbers_without_a_dot_are_numbers_on_the_command_line_and_in_yaml(tmp_path):
    # PyYAML reads YAML 1.1, where 1e-6 is a string: --meta inner_lr=1e-6 was refused.
    from rl_scan.cli.env_args import parse_set
    from rl_scan.config import load_yaml

    assert parse_set(["inner_lr=1e-6", "a.b=3E2", "c=-1.5e+3", "d=1e", "e=e5"]) == {
        "inner_lr": 1e-6, "a": {"b": 300.0}, "c": -1500.0, "d": "1e", "e": "e5"}
    path = tmp_path / "env.yaml"
    path.write_text("quad: {sensor_range: 35e-1}\nscenario: 'test:1'\n")
    assert load_yaml(path) == {"quad": {"sensor_range": 3.5}, "scenario": "test:1"}


@pytest.mark.parametrize("argv, field", [
    (["render", "--scenario", "ablation", "--policy", "greedy", "--out", "/proc/x/a.gif"],
     "out"),
    (["replay", "--out", "/proc/x/r.html"], "out"),
    (["report", "/tmp", "--out", "/proc/report"], "out"),
    (["train", "--results", "/proc/results"], "results"),
    (["scenario", "export", "ablation", "/proc/scene.obj"], "out"),
    (["bench", "env", "--json", "/proc/b/x.json"], "json"),
])
def test_an_output_path_that_cannot_be_written_is_one_line_before_any_work(
        capsys, argv, field):
    code, out, err = run(capsys, *argv)
    assert code == 2 and out == ""
    assert f"error: {field}='/proc/" in err and "no folder can be made in '/proc'" in err
    assert len(err.strip().splitlines()) == 1


def test_an_address_where_no_cluster_runs_is_one_line_within_seconds(capsys, tmp_path):
    import socket
    import time

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    start = time.monotonic()
    code, _, err = run(capsys, "train", "--preset", "smoke", "--address", f"127.0.0.1:{port}",
                       "--results", str(tmp_path))
    assert code == 2 and time.monotonic() - start < 30
    assert f"address='127.0.0.1:{port}' is invalid" in err and "nothing answers" in err
    assert not any(tmp_path.iterdir())
    code, _, err = run(capsys, "train", "--preset", "smoke", "--address", "headnode",
                       "--results", str(tmp_path))
    assert code == 2 and "HOST:PORT" in err


def test_an_output_under_a_file_is_refused(capsys, tmp_path):
    (tmp_path / "file").write_text("")
    code, _, err = run(capsys, "render", "--out", str(tmp_path / "file" / "a.gif"))
    assert code == 2 and "is a file" in err
    assert [p.name for p in tmp_path.iterdir()] == ["file"]  # no probe left behind


@pytest.mark.parametrize("argv", [[], ["scenario"], ["bench", "env"], ["render"]])
def test_help(capsys, argv):
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0
    assert "usage: rl-scan" in capsys.readouterr().out


def test_every_help_page_renders_its_percent_signs():
    """Descriptions are not %-formatted by argparse (help strings are): no stray '%%'."""
    import argparse

    from rl_scan.cli.parser import build_parser

    def pages(parser):
        yield parser.format_help()
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    yield from pages(sub)

    texts = list(pages(build_parser()))
    assert len(texts) > 15
    assert not [t.splitlines()[0] for t in texts if "%%" in t]
