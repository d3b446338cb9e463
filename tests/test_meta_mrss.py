"""The meta-MRSS protocol: input checks, MetaPOCA's settings per preset, curve metrics and
the summary by hand, and one end-to-end smoke protocol through Tune (meta-train, adapt,
standard POCA)."""

from __future__ import annotations

import json
import math
import os
import sys

import pytest

from rl_scan import results as R
from rl_scan.cli import main
from rl_scan.config import ConfigError
from rl_scan.metrics import curve_metrics
from rl_scan.tuning.meta_mrss import (
    PROTOCOLS,
    check_jobs,
    format_table,
    parse_tests,
    plan_jobs,
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
    (["--seed", "-1"], "seed=-1"),
    (["--tests", "train:1"], "train set"),
    (["--jobs", "0"], "jobs=0"),
    (["--meta", "relabel_query=true", "--meta", "outer=maml"], "relabel_query=True"),
    (["--meta", "tasks=2", "--methods", "dr,poca"], "meta='tasks=2'"),
    # one more run at a time than this machine's CPUs hold (smoke runs take one CPU each)
    (["--jobs", str(os.cpu_count() + 1)], f"jobs={os.cpu_count() + 1} is invalid: allowed at "
                                          f"most {os.cpu_count()}"),
])
def test_bad_protocol_input_fails_before_training(tmp_path, capsys, argv, message):
    code = main(["experiment", "meta-mrss", "--preset", "smoke", "--results", str(tmp_path),
                 *argv])
    assert code == 2 and message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written


def test_every_paper_run_is_checked_up_front_and_meta_poca_samples_locally(tmp_path):
    plan = plan_jobs(tmp_path, ["meta-mrss", "dr", "transfer", "poca"], ["test:0", "test:4"],
                     seeds=2, protocol=PROTOCOLS["paper"], env_config={})
    assert len(plan) == 2 * (3 + 4 * 2)
    meta = next(j for j in plan if j.name == "meta-mrss_s0")
    assert meta.kwargs["preset_overrides"]["num_env_runners"] == 0
    check_jobs(plan)  # the paper preset's 2 env runners would be refused by MetaPOCA
    adapt = [j for j in plan if j.name == "dr_test4_s1"][0]
    assert adapt.after.name == "dr_s1"
    assert adapt.kwargs["init_from"] == tmp_path / R.PRETRAIN_DIR / "dr_s1"
    assert all(j.after is None for j in plan if j.name.startswith("poca_"))
    for protocol in PROTOCOLS.values():  # every protocol's budgets fit every method
        check_jobs(plan_jobs(tmp_path, ["meta-mrss", "dr", "transfer", "poca"], ["test:0"],
                             seeds=1, protocol=protocol, env_config={}))
    with pytest.raises(ConfigError, match="comm_scheme"):
        check_jobs(plan_jobs(tmp_path, ["poca"], ["test:0"], 1, PROTOCOLS["smoke"],
                             {"comm_scheme": 9}))


def test_a_protocol_run_a_seed_at_a_time_plans_and_summarises_that_seed_only(tmp_path):
    """--seed 2 --seeds 1: every run is seed 2's (names, seeds, the adaptation's start),
    and its summary reads seed 2's curves, not seed 0's beside them."""
    plan = plan_jobs(tmp_path, ["dr", "poca"], ["test:0"], seeds=1,
                     protocol=PROTOCOLS["quick"], env_config={}, first_seed=2)
    assert [(j.name, j.kwargs["seed"]) for j in plan] == [
        ("dr_s2", 2), ("dr_test0_s2", 2), ("poca_test0_s2", 2)]
    assert plan[1].kwargs["init_from"] == tmp_path / R.PRETRAIN_DIR / "dr_s2"
    _eval_file(tmp_path, "poca", "test:0", 0, [(400, 0.1)])
    _eval_file(tmp_path, "poca", "test:0", 2, [(400, 0.7)])
    s = summarize(tmp_path, ["poca"], ["test:0"], seeds=1, budget=400, first_seed=2)
    assert s["methods"]["poca"]["final_coverage"]["values"] == pytest.approx([0.7])
    assert s["common"] == ["test:0 s2"] and not s["missing"]


def test_meta_settings_reach_meta_mrss_pretraining_only_and_a_rerun_must_keep_them(
        tmp_path, capsys):
    plan = plan_jobs(tmp_path, ["meta-mrss", "dr"], ["test:0"], seeds=1,
                     protocol=PROTOCOLS["quick"], env_config={},
                     meta_settings={"relabel_query": True})
    settings = {j.name: j.kwargs.get("settings_overrides") for j in plan}
    assert settings == {"meta-mrss_s0": {"relabel_query": True}, "meta-mrss_test0_s0": None,
                        "dr_s0": None, "dr_test0_s0": None}
    with pytest.raises(ConfigError, match="inner_adam=.adamw. is invalid"):
        check_jobs(plan_jobs(tmp_path, ["meta-mrss"], ["test:0"], 1, PROTOCOLS["quick"], {},
                             meta_settings={"inner_adam": "adamw"}))
    # an experiment started with other settings is refused, before Ray starts
    folder = tmp_path / "meta-mrss"
    folder.mkdir()
    R.write_yaml(folder / R.PROTOCOL_FILE, {"meta_settings": {"relabel_query": True}})
    code = main(["experiment", "meta-mrss", "--preset", "smoke", "--results", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and "meta='(none)' is invalid" in err and "relabel_query" in err


def test_curve_metrics_by_hand():
    curve = [{"env_steps": 400, "coverage": 0.5, "success": 0.0},
             {"env_steps": 800, "coverage": 0.82, "success": 0.0},
             {"env_steps": 1200, "coverage": 0.97, "success": 2 / 3}]
    got = curve_metrics(curve, budget=1600)
    assert math.isnan(got.pop("start_coverage"))  # no evaluation 0: started from scratch
    # area: 0.5 held over [0, 400], trapezoids to 1200, 0.97 held to the budget:
    # (200 + 264 + 358 + 388) / 1600
    assert got == pytest.approx({"final_coverage": 0.97, "steps_to_80": 800.0,
                                 "reached_80": 1.0, "auc": 1210 / 1600, "success": 2 / 3})
    never = curve_metrics(curve[:1], budget=1600)
    assert never["steps_to_80"] == 1600 and never["reached_80"] == 0  # censored at the budget
    noisy = curve_metrics([{"env_steps": 400, "coverage": 0.85}, {"env_steps": 800,
                           "coverage": 0.6}, {"env_steps": 1200, "coverage": 0.9}], 1600)
    assert noisy["steps_to_80"] == 1600  # no two consecutive evaluations at 80 %
    warm = curve_metrics([{"env_steps": 0, "coverage": 0.85, "success": 0.0}, *curve], 1600)
    assert warm["start_coverage"] == 0.85 and warm["steps_to_80"] == 800.0


def _eval_file(root, method, test, seed, points):
    run = root / R.ADAPT_DIR / f"{method}_{test.replace(':', '')}_s{seed}"
    run.mkdir(parents=True)
    (run / R.EVAL_FILE).write_text(json.dumps(
        [{"env_steps": s, "coverage": c, "success": float(c >= 0.95)} for s, c in points]))


def test_summary_means_and_stds_over_seeds_by_hand(tmp_path):
    """Budget 400. poca lacks test1 s1, so meta-mrss's test1 s1 is left out: both methods
    are summarised on (test0 s0, test1 s0, test0 s1)."""
    _eval_file(tmp_path, "meta-mrss", "test:0", 0, [(0, 0.3), (200, 0.8), (400, 0.9)])
    _eval_file(tmp_path, "meta-mrss", "test:1", 0, [(0, 0.5), (200, 0.7), (400, 0.96)])
    _eval_file(tmp_path, "meta-mrss", "test:0", 1, [(200, 0.5), (400, 0.6)])
    _eval_file(tmp_path, "meta-mrss", "test:1", 1, [(200, 0.81), (400, 0.85)])
    _eval_file(tmp_path, "poca", "test:0", 0, [(200, 0.1), (400, 0.2)])
    _eval_file(tmp_path, "poca", "test:1", 0, [(200, 0.3), (400, 0.4)])
    _eval_file(tmp_path, "poca", "test:0", 1, [(200, 0.2), (400, 0.3)])
    s = summarize(tmp_path, ["meta-mrss", "poca"], ["test:0", "test:1"], seeds=2, budget=400)
    assert s["left_out"] == ["meta-mrss_test1_s1"] and len(s["missing"]) == 1
    meta = s["methods"]["meta-mrss"]
    # seed 0: finals .9, .96 -> .93; seed 1: test0 only -> .6
    assert meta["final_coverage"]["values"] == pytest.approx([0.93, 0.6])
    assert meta["final_coverage"]["std"] == pytest.approx(0.33 / 2 ** 0.5)  # sample std
    # steps to 80 %: seed 0 test0 at 200 (200 and 400 >= .8), test1 censored at 400 (only
    # its last evaluation is >= .8); seed 1 test0 censored -> 300 and 400
    assert meta["steps_to_80"]["values"] == pytest.approx([300.0, 400.0])
    assert meta["reached_80"]["values"] == pytest.approx([0.5, 0.0])
    # areas: test0 s0 (110 + 170) / 400, test1 s0 (120 + 166) / 400, test0 s1 (100 + 110) / 400
    assert meta["auc"]["values"] == pytest.approx([(0.7 + 0.715) / 2, 0.525])
    assert meta["success"]["values"] == pytest.approx([0.5, 0.0])
    assert meta["start_coverage"]["values"][0] == pytest.approx(0.4)  # (.3 + .5) / 2
    assert math.isnan(meta["start_coverage"]["values"][1])
    poca = s["methods"]["poca"]
    assert poca["final_coverage"]["values"] == pytest.approx([0.3, 0.3])
    assert poca["auc"]["values"] == pytest.approx([(0.125 + 0.325) / 2, 0.225])
    rows = format_table(s).splitlines()
    assert rows[2] == ("| meta-mrss | 40.0 ± 0.0 | 76.5 ± 23.3 | 350 ± 71 (25 %) | "
                       "61.6 ± 12.9 | 25.0 ± 35.4 | 87.12 |")
    assert rows[3] == "| poca | - | 30.0 ± 0.0 | 400 ± 0 (0 %) | 22.5 ± 0.0 | 0.0 ± 0.0 | 60.16 |"
    table = "\n".join(rows)
    assert "(censored): 0.88 (goal <= 0.30)" in table  # 350 / 400
    assert "missing runs (1): poca_test1_s1" in table and "left out" in table


def test_meta_training_diagnostics_are_summarised_over_the_last_half(tmp_path):
    """Gain = query - support coverage, mean over the last half of the meta-iterations,
    then mean and sample std over seeds; the table prints it."""
    _eval_file(tmp_path, "meta-mrss", "test:0", 0, [(200, 0.5)])
    for seed, metas in ((0, [(0.1, 0.0, 2.0), (0.2, 0.3, 1.0), (0.3, 0.5, 3.0)]),
                        (1, [(0.1, 0.4, 9.0), (0.4, 0.4, 1.0)])):
        run = tmp_path / R.PRETRAIN_DIR / f"meta-mrss_s{seed}"
        run.mkdir(parents=True)
        for it, (before, after, norm) in enumerate(metas, start=1):
            R.append_meta(run, {R.ITERATION: it, R.ENV_STEPS: 100 * it, R.META_BEFORE: before,
                                R.META_AFTER: after, R.META_DELTA_NORM: norm})
    s = summarize(tmp_path, ["meta-mrss"], ["test:0"], seeds=2, budget=400)
    # seed 0: last half = iterations 2, 3: gains .1, .2 -> .15, norms 1, 3 -> 2
    # seed 1: iteration 2: gain 0, norm 1
    assert s["meta_training"]["gain"]["values"] == pytest.approx([0.15, 0.0])
    assert s["meta_training"]["delta_norm"]["values"] == pytest.approx([2.0, 1.0])
    assert s["meta_training"]["gain"]["std"] == pytest.approx(0.15 / 2 ** 0.5)
    assert "adaptation gain (query coverage with the adapted weights - support coverage " \
           "with the meta weights) +7.5 ± 10.6 points; inner-update step ||delta|| 1.5" \
           in format_table(s)


@pytest.mark.slow
def test_smoke_protocol_end_to_end(ray_session, tmp_path):
    summary = run_protocol(tmp_path, "mm", preset="smoke", methods=["meta-mrss", "poca"],
                           tests=["test:0"], seeds=1)
    root = tmp_path / "mm"
    assert (root / R.PRETRAIN_DIR / "meta-mrss_s0" / R.DONE).is_file()
    meta_run = root / R.ADAPT_DIR / "meta-mrss_test0_s0"
    import yaml

    run = yaml.safe_load((meta_run / R.RUN_FILE).read_text())
    assert run["init_from"] and "meta-mrss_s0" in run["init_from"]
    assert run["env_config"]["scenario"] == "test:0"
    for method in ("meta-mrss", "poca"):
        curve = summary["methods"][method]["runs"][f"{method}_test0_s0"]["curve"]
        evals = PROTOCOLS["smoke"].adapt_steps // 400  # one per iteration
        # a pre-trained start is also evaluated before adaptation (evaluation 0)
        assert [s for s, _ in curve] == [0] * (method == "meta-mrss") + [
            400 * (i + 1) for i in range(evals)]
        assert all(0.0 <= c <= 1.0 for _, c in curve)
    entries = json.loads((meta_run / R.EVAL_FILE).read_text())
    assert entries[0]["training_iteration"] == 0
    assert set(entries[1]) - set(entries[0]) <= {"module_returns"}  # the same metrics
    assert not summary["missing"]
    assert (root / R.TABLE_FILE).read_text().count("|") > 10


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


@pytest.mark.slow
def test_ctrl_c_stops_parallel_runs_unfinished_and_a_rerun_completes_them(tmp_path):
    """Ctrl+C reaches both child runs; neither is marked done; the same command resumes."""
    import os
    import signal
    import subprocess
    import time

    cmd = [sys.executable, "-m", "rl_scan.cli", "experiment", "meta-mrss", "--preset", "smoke",
           "--methods", "poca", "--tests", "0,1", "--seeds", "1", "--adapt-steps", "6000",
           "--jobs", "2", "--results", str(tmp_path), "--name", "mm"]
    # SIGINT back to default in the child: a test run started in the background by a
    # non-interactive shell inherits SIGINT ignored, and Python then never raises
    # KeyboardInterrupt (the command would finish with 0).
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    adapt = tmp_path / "mm" / R.ADAPT_DIR
    runs = [adapt / "poca_test0_s0", adapt / "poca_test1_s0"]
    deadline = time.time() + 180
    # A worker writes a checkpoint before the driver has recorded that iteration's
    # evaluation: wait for both, or a fast iteration can be stopped in between.
    while time.time() < deadline and not all(
            list((r / R.TUNE_DIR / R.TRAIN_TRIAL).glob("checkpoint_*"))
            and (r / R.EVAL_FILE).is_file() for r in runs):
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGINT)  # the parent only: it passes Ctrl+C on to its runs
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "interrupted" in err, err[-2000:]
    assert not any((r / R.DONE).exists() for r in runs)
    stopped_at = [json.loads((r / R.EVAL_FILE).read_text())[-1]["env_steps"]
                  for r in runs]
    assert all(s < 6000 for s in stopped_at)
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    for run in runs:
        assert (run / R.DONE).is_file()
        iters = [e["training_iteration"] for e in json.loads((run / R.EVAL_FILE)
                                                               .read_text())]
        assert iters == list(range(1, 16))  # resumed, not restarted: each iteration once
        # runs started side by side keep apart (a shared Ray session mixed their trials)
        assert [p.name for p in (run / R.TUNE_DIR).glob("trial*")] == [R.TRAIN_TRIAL]


def test_a_meta_iteration_spends_its_settings_steps_and_the_budget_is_a_whole_number_of_them():
    from rl_scan.tuning.driver import make_run_spec

    budget = {"total_env_steps": 100_000}
    meta = make_run_spec("meta-poca", {}, "quick", preset_overrides=budget)
    assert meta.settings.env_steps_per_iteration() == 4 * (500 + 500)  # DR's batch
    assert (meta.settings.outer, meta.settings.inner_adam) == ("maml_dr", "meta")
    assert meta.algorithm_config().num_envs_per_env_runner == 1  # task_envs: 4 scenes each
    assert meta.iterations == 25
    assert make_run_spec("poca", {}, "quick", preset_overrides=budget).iterations == 25
    assert make_run_spec("meta-poca", {}, "paper").iterations == 40  # 8M / 200k
    reptile = make_run_spec("meta-poca", {}, "quick", preset_overrides=budget,
                            settings_overrides={"outer": "reptile", "query_steps": 750})
    assert reptile.settings.outer == "reptile" and reptile.iterations == 20  # 5k each
    assert reptile.metadata()["algo_settings"]["query_steps"] == 750


def test_meta_poca_evaluates_and_checkpoints_at_the_presets_env_step_spacing():
    from rl_scan.tuning.driver import make_run_spec

    quick = make_run_spec("poca", {}, "quick").preset  # every 5 x 4,000 env steps
    assert (quick.evaluation_interval, quick.checkpoint_frequency) == (5, 5)
    meta = make_run_spec("meta-poca", {}, "quick").preset  # 4,000 per meta-iteration
    assert (meta.evaluation_interval, meta.checkpoint_frequency) == (5, 5)
    many = make_run_spec("meta-poca", {}, "quick", settings_overrides={"tasks": 20}).preset
    assert (many.evaluation_interval, many.checkpoint_frequency) == (1, 1)  # 20,000 each
    paper = make_run_spec("meta-poca", {}, "paper").preset  # 102,400 vs 200,000: at least 1
    assert paper.evaluation_interval == 1
