"""The meta-MRSS protocol: input checks, curve metrics and the summary by hand, and one
end-to-end smoke protocol through Tune (meta-train, adapt, standard POCA)."""

from __future__ import annotations

import json
import math

import pytest

from rl_scan.cli import main
from rl_scan.config import ConfigError
from rl_scan.tuning.meta_mrss import (
    PROTOCOLS,
    curve_metrics,
    format_table,
    parse_tests,
    run_protocol,
    summarize,
)


def test_tests_must_be_held_out_scenarios():
    assert parse_tests("0, 3,test:4") == ["test:0", "test:3", "test:4"]
    with pytest.raises(ConfigError, match="train set"):
        parse_tests("train:3")
    with pytest.raises(ConfigError, match="tests"):
        parse_tests("7")


@pytest.mark.parametrize("argv, message", [
    (["--methods", "maml"], "methods='maml'"),
    (["--adapt-steps", "0"], "adapt_steps=0"),
    (["--seeds", "0"], "seeds=0"),
    (["--tests", "train:1"], "train set"),
])
def test_bad_protocol_input_fails_before_training(tmp_path, capsys, argv, message):
    code = main(["experiment", "meta-mrss", "--preset", "smoke", "--results", str(tmp_path),
                 *argv])
    assert code == 2 and message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written


def test_curve_metrics_by_hand():
    curve = [{"env_steps": 400, "coverage": 0.5, "success": 0.0},
             {"env_steps": 800, "coverage": 0.82, "success": 0.0},
             {"env_steps": 1200, "coverage": 0.97, "success": 2 / 3}]
    assert curve_metrics(curve) == {"final_coverage": 0.97, "steps_to_80": 800.0,
                                    "success": 2 / 3}
    never = curve_metrics(curve[:1])
    assert math.isnan(never["steps_to_80"]) and never["final_coverage"] == 0.5


def _eval_file(root, method, test, seed, points):
    run = root / "adapt" / f"{method}_{test.replace(':', '')}_s{seed}"
    run.mkdir(parents=True)
    (run / "eval_metrics.json").write_text(json.dumps(
        [{"env_steps": s, "coverage": c, "success": float(c >= 0.95)} for s, c in points]))


def test_summary_means_and_stds_over_seeds_by_hand(tmp_path):
    # seed 0: test0 reaches 80 % at 200 (final .9), test1 at 400 (final .96)
    # seed 1: test0 never (final .6), test1 at 200 (final .85); test1 of "poca" is missing
    _eval_file(tmp_path, "meta-mrss", "test:0", 0, [(200, 0.8), (400, 0.9)])
    _eval_file(tmp_path, "meta-mrss", "test:1", 0, [(200, 0.7), (400, 0.96)])
    _eval_file(tmp_path, "meta-mrss", "test:0", 1, [(200, 0.5), (400, 0.6)])
    _eval_file(tmp_path, "meta-mrss", "test:1", 1, [(200, 0.81), (400, 0.85)])
    _eval_file(tmp_path, "poca", "test:0", 0, [(200, 0.1), (400, 0.2)])
    s = summarize(tmp_path, ["meta-mrss", "poca"], ["test:0", "test:1"], seeds=2)
    meta = s["methods"]["meta-mrss"]
    # per-seed final coverage: (.9+.96)/2 = .93 and (.6+.85)/2 = .725
    assert meta["final_coverage"]["values"] == pytest.approx([0.93, 0.725])
    assert meta["final_coverage"]["mean"] == pytest.approx(0.8275)
    assert meta["final_coverage"]["std"] == pytest.approx(0.1025)  # population std
    # steps to 80 % among runs that reached it: seed 0 (200+400)/2 = 300, seed 1: 200
    assert meta["steps_to_80"]["values"] == pytest.approx([300.0, 200.0])
    assert meta["reached_80"]["values"] == pytest.approx([1.0, 0.5])
    assert meta["success"]["values"] == pytest.approx([0.5, 0.0])
    assert len(s["missing"]) == 3  # poca: test1 s0, test0 s1, test1 s1
    table = format_table(s)
    assert "87.12" in table and "60.16" in table and "missing runs (3)" in table


@pytest.mark.slow
def test_smoke_protocol_end_to_end(ray_session, tmp_path):
    summary = run_protocol(tmp_path, "mm", preset="smoke", methods=["meta-mrss", "poca"],
                           tests=["test:0"], seeds=1)
    root = tmp_path / "mm"
    assert (root / "pretrain" / "meta-mrss_s0" / "DONE").is_file()
    meta_run = root / "adapt" / "meta-mrss_test0_s0"
    import yaml

    run = yaml.safe_load((meta_run / "run.yaml").read_text())
    assert run["init_from"] and "meta-mrss_s0" in run["init_from"]
    assert run["env_config"]["scenario"] == "test:0"
    for method in ("meta-mrss", "poca"):
        curve = summary["methods"][method]["runs"][f"{method}_test0_s0"]["curve"]
        assert len(curve) == PROTOCOLS["smoke"].adapt_steps // 400  # one eval per iteration
        assert all(0.0 <= c <= 1.0 for _, c in curve)
    assert not summary["missing"]
    assert (root / "table.md").read_text().count("|") > 10


def test_init_from_loads_every_shared_module_into_learner_and_runner(ray_session, tmp_path):
    import torch

    from rl_scan.algorithms.init_weights import init_from_callback
    from rl_scan.algorithms.poca import poca_config

    def build(seed, init=None):
        config = poca_config({"max_steps": 20}, train_batch_size=80, minibatch_size=64,
                             num_epochs=1, num_envs_per_env_runner=1, seed=seed)
        if init:
            config.callbacks(on_algorithm_init=init_from_callback(init))
        return config.build_algo()

    source = build(seed=1)
    source.train()
    source.save_to_path(str(tmp_path / "ckpt"))
    want = {m: source.learner_group._learner.module[m].state_dict()
            for m in ("wheeled", "quad", "critic")}
    source.stop()
    fresh, started = build(seed=2), build(seed=2, init=tmp_path / "ckpt")
    for m, sd in want.items():
        got = started.learner_group._learner.module[m].state_dict()
        other = fresh.learner_group._learner.module[m].state_dict()
        assert all(torch.equal(sd[k], got[k]) for k in sd), m
        assert not all(torch.equal(sd[k], other[k]) for k in sd), m  # seeds differ
        if m != "critic":  # the sampling actors carry the loaded weights too
            runner = started.env_runner.module[m].state_dict()
            assert all(torch.equal(sd[k], runner[k]) for k in runner), m
    fresh.stop()
    started.stop()
