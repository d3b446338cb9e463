"""Training launches through Tune: run folder contents, and SIGKILL -> --resume."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from PIL import Image

from rl_scan import results as R
from rl_scan.cli import main
from rl_scan.config import ConfigError
from rl_scan.tuning.launch import check_resources, train
from rl_scan.tuning.presets import get_preset


def _progress(run_dir: Path) -> list[dict]:
    with open(run_dir / R.TUNE_DIR / R.TRAIN_TRIAL / R.PROGRESS_FILE) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def ppo_run(ray_session, tmp_path_factory):
    """One PPO smoke run (2 iterations of 400 env steps) shared by the tests below."""
    return train("ppo", {"scenario": "test:2"}, "smoke", seed=3,
                 results_dir=tmp_path_factory.mktemp("results"))


def test_ppo_smoke_run_writes_a_complete_run_folder(ppo_run):
    run_dir = ppo_run
    meta = yaml.safe_load((run_dir / R.RUN_FILE).read_text())
    assert meta["algo"] == "ppo" and meta["seed"] == 3 and len(meta["git_commit"]) >= 7
    assert meta["env_config"]["scenario"] == "test:2"
    assert meta["env_config"]["max_steps"] == 50  # the smoke preset's env override
    # what can change a seeded run's numbers: the compiler of the raycasts, the mesher
    assert {"torch", "numba", "llvmlite", "trimesh"} <= set(meta["versions"])
    assert meta["versions"]["numba"][0].isdigit()
    evals = json.loads((run_dir / R.EVAL_FILE).read_text())
    assert [e["training_iteration"] for e in evals] == [1, 2]
    assert all(0.0 <= e["coverage"] <= 1.0 and e["episode_steps"] <= 50 for e in evals)
    rows = _progress(run_dir)
    assert [int(float(r[R.ENV_STEPS])) for r in rows] == [400, 800]
    assert sorted(p.name for p in (run_dir / R.TUNE_DIR / R.TRAIN_TRIAL).glob("checkpoint_*"))
    assert list((run_dir / R.TUNE_DIR / R.TRAIN_TRIAL).glob("events.out.tfevents*"))
    import ray  # the node it ran on: this session's only node; no remote env runners

    nodes = json.loads((run_dir / R.NODES_FILE).read_text())
    assert nodes == [{"from_iteration": 1, "env_runners": [], "trainable": {
        "node_id": ray.nodes()[0]["NodeID"], "ip": ray.nodes()[0]["NodeManagerAddress"]}}]
    with pytest.raises(ConfigError, match="exists: pass --resume"):
        train("ppo", {"scenario": "test:2"}, "smoke", results_dir=run_dir.parent,
              name=run_dir.name)


def test_evaluate_and_render_a_checkpoint(ppo_run, tmp_path, capsys, monkeypatch):
    """The CLI plays the trained modules on the run's env config (test:2, 50-step episodes)."""
    out_json, gif = tmp_path / "eval.json", tmp_path / "team.gif"
    assert main(["evaluate", str(ppo_run), "--episodes", "2", "--json", str(out_json)]) == 0
    res = json.loads(out_json.read_text())
    assert len(res["episodes"]) == 2
    assert all(e["episode_steps"] == 50 and e["cells_total"] == 207 for e in res["episodes"])
    assert "greedy team mean" in capsys.readouterr().out
    monkeypatch.chdir(ppo_run.parent)  # a relative run path, as the README uses
    assert main(["render", ppo_run.name, "--out", str(gif), "--every", "10"]) == 0
    assert Image.open(gif).n_frames == 6
    assert main(["evaluate", str(tmp_path)]) == 2  # no checkpoint there: one-line error


def test_deterministic_evaluation_plays_the_mean_action(ppo_run, tmp_path):
    """``evaluate --deterministic``: every robot's action is its Gaussian's mean (clipped),
    whatever torch's seed; sampled actions (the default) are not."""
    import numpy as np
    import torch
    from ray.rllib.core.columns import Columns

    from rl_scan.algorithms.rollout import (
        PolicyTeam,
        load_actors,
        resolve_checkpoint,
        run_env_config,
    )
    from rl_scan.envs.core import ScanCore

    ckpt = resolve_checkpoint(ppo_run)
    modules = load_actors(ckpt)
    obs = ScanCore(run_env_config(ckpt)).reset(seed=0)
    mean = {}
    for aid, o in obs.items():
        module = modules[aid.rsplit("_", 1)[0]]
        logits = module.forward_inference({Columns.OBS: torch.as_tensor(o[None])})
        inputs = logits[Columns.ACTION_DIST_INPUTS][0].detach().numpy()
        mean[aid] = np.clip(inputs[:len(inputs) // 2], -1, 1)
    for seed in (0, 1):
        torch.manual_seed(seed)
        acts = PolicyTeam(modules, explore=False).act(obs)
        for aid in obs:
            np.testing.assert_allclose(acts[aid], mean[aid], rtol=1e-6, atol=1e-7)
    sampled = PolicyTeam(modules).act(obs)
    assert not all(np.allclose(sampled[a], mean[a]) for a in obs)
    out_json = tmp_path / "det.json"
    assert main(["evaluate", str(ppo_run), "--deterministic", "--episodes", "1",
                 "--no-reference", "--json", str(out_json)]) == 0
    assert json.loads(out_json.read_text())["deterministic"] is True


def test_best_checkpoints_are_kept_and_re_evaluated_for_the_report(ray_session, tmp_path,
                                                                   capsys):
    """6 iterations, a checkpoint each: Tune keeps the 3 best by evaluation coverage plus the
    latest; `evaluate --best` plays the best one and records it in the run folder."""
    run = train("ppo", {"scenario": "test:2"}, "smoke", seed=1, results_dir=tmp_path,
                preset_overrides={"total_env_steps": 2400})
    cov = {e["training_iteration"]: e["coverage"]
           for e in json.loads((run / R.EVAL_FILE).read_text())}
    assert sorted(cov) == [1, 2, 3, 4, 5, 6]
    # checkpoint_00000k holds iteration k+1
    trial = run / R.TUNE_DIR / R.TRAIN_TRIAL
    kept = {int(p.name.split("_")[1]) + 1 for p in trial.glob("checkpoint_*")}
    deleted = set(cov) - kept
    assert 6 in kept and len(kept) == (3 if 6 in sorted(cov, key=cov.get)[-3:] else 4)
    assert min(cov[i] for i in kept - {6}) >= max(cov[i] for i in deleted)
    assert main(["evaluate", str(run), "--best", "--episodes", "2", "--no-reference"]) == 0
    best = json.loads((run / R.BEST_EVAL_FILE).read_text())
    assert best["eval_coverage"] == pytest.approx(max(cov.values()))
    assert cov[best["training_iteration"]] == pytest.approx(max(cov.values()))
    assert best["env_steps"] == 400 * best["training_iteration"]
    assert len(best["coverage"]) == 2 and best["scenario"] == "test:2"
    assert "recorded in" in capsys.readouterr().out


def test_bad_input_fails_before_ray_work(tmp_path):
    with pytest.raises(ConfigError, match="algo='dqn'"):
        train("dqn", {}, "smoke", results_dir=tmp_path)
    with pytest.raises(ConfigError, match="preset='huge'"):
        train("ppo", {}, "huge", results_dir=tmp_path)
    with pytest.raises(ConfigError, match="unknown config key 'max_step'"):
        train("ppo", {"max_step": 3}, "smoke", results_dir=tmp_path)
    assert list(tmp_path.iterdir()) == []  # nothing half-written



def test_a_run_another_process_is_writing_is_refused(ray_session, tmp_path, capsys,
                                                      held_elsewhere):
    """A second `rl-scan train --resume` beside the first would train the run twice into
    the same files: it is refused before it writes anything."""
    with held_elsewhere(tmp_path, "run"):  # as a running `rl-scan train` holds it
        code = main(["train", "--algo", "ppo", "--preset", "smoke", "--results",
                     str(tmp_path), "--name", "run"])
    assert code == 2
    assert ("name='run' is invalid: allowed a run no other process is running"
            in capsys.readouterr().err)
    assert not (tmp_path / "run").exists()


def test_resources_are_checked_before_launch():
    check_resources(get_preset("smoke", {"num_env_runners": 1}), available=2)
    with pytest.raises(ConfigError, match="num_env_runners=2 is invalid: allowed at most 1"):
        check_resources(get_preset("smoke", {"num_env_runners": 2}), available=2)
    check_resources(get_preset("smoke", {"learner_cpus": 2}), available=2)
    with pytest.raises(ConfigError, match="learner_cpus=3 is invalid: allowed at most 2 "):
        check_resources(get_preset("smoke", {"learner_cpus": 3}), available=2)
    with pytest.raises(ConfigError, match="num_env_runners=1 is invalid: allowed at most 0 "):
        check_resources(get_preset("smoke", {"learner_cpus": 2, "num_env_runners": 1}),
                        available=2)
    with pytest.raises(ConfigError, match="preset.learner_cpus=0 is invalid"):
        get_preset("smoke", {"learner_cpus": 0})
    # custom resources: the first bundle must fit on one node
    slot = get_preset("smoke", {"custom_resources": {"trial_slot": 1.0}})
    check_resources(slot, available=2, custom={"trial_slot": 1.0})
    with pytest.raises(ConfigError, match=r"custom_resources=\{'trial_slot': 1.0\} is invalid"
                                          r": allowed resources one node .* at most 0.5"):
        check_resources(slot, available=2, custom={"trial_slot": 0.5})
    with pytest.raises(ConfigError, match="not CPU/GPU/memory"):
        get_preset("smoke", {"custom_resources": {"CPU": 1.0}})


@pytest.mark.parametrize("overrides, threads", [({"num_env_runners": 1}, 1),
                                                ({"learner_cpus": 2}, 2)])
def test_a_run_gets_the_cpus_it_reserves(ray_session, tmp_path, overrides, threads):
    """A remote env runner gets a CPU of the run's own placement group (not a hang), and
    the learner runs as many torch threads as the run reserves CPUs for it."""
    run_dir = train("ppo", {"scenario": "test:2"}, "smoke", results_dir=tmp_path,
                    preset_overrides=overrides)
    rows = _progress(run_dir)
    assert [int(float(r[R.ENV_STEPS])) for r in rows] == [400, 800]
    assert {int(r[R.LEARNER_THREADS]) for r in rows} == {threads}


@pytest.mark.slow
def test_sigkill_then_resume_continues_from_a_checkpoint(tmp_path):
    """A run killed mid-training resumes from a checkpoint, not from scratch, counters
    intact. The checkpoint is the last one Tune's saved state names: a SIGKILL just after a
    checkpoint is written can land before Tune records it (seen idle in CI), and then the
    iterations after the recorded one are run again; reports keep each one's last result."""
    cmd = [sys.executable, "-m", "rl_scan.cli", "train", "--algo", "ppo", "--preset", "smoke",
           "--total-env-steps", "4000", "--results", str(tmp_path), "--name", "run"]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    trial = tmp_path / "run" / R.TUNE_DIR / R.TRAIN_TRIAL
    deadline = time.time() + 120
    while time.time() < deadline and len(list(trial.glob("checkpoint_*"))) < 3:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    # checkpoint_00000k holds iteration k+1
    restored_from = max(int(p.name.split("_")[1]) for p in trial.glob("checkpoint_*")) + 1
    assert 2 <= restored_from < 10, "kill should land mid-run"
    out = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = _progress(tmp_path / "run")
    iters = [int(r["training_iteration"]) for r in rows]
    steps = [int(float(r[R.ENV_STEPS])) for r in rows]
    assert iters[-1] == 10 and steps[-1] == 4000
    # A restart from scratch would log iteration 1 (and 400 env steps) again; a restore runs
    # again only iterations after a checkpoint, at most the ones since the last on disk.
    assert iters.count(1) == 1 and steps.count(400) == 1
    repeated = {i for i in iters if iters.count(i) > 1}
    assert repeated <= set(range(2, restored_from + 1)), (repeated, restored_from)
    merged = R.progress_rows(tmp_path / "run")
    assert [int(r[R.ITERATION]) for r in merged] == list(range(1, 11))
    assert [int(float(r[R.ENV_STEPS])) for r in merged] == [400 * k for k in range(1, 11)]
    evals = json.loads((tmp_path / "run" / R.EVAL_FILE).read_text())
    logged = [e["training_iteration"] for e in evals]
    assert logged == sorted(set(logged)) and logged[-1] == 10
    assert restored_from + 1 in logged  # the first iteration after the restore


@pytest.mark.slow
def test_a_resume_survives_tune_having_deleted_the_checkpoint_its_state_names(tmp_path):
    """Tune can delete the checkpoint its saved state names as the latest (a new one
    registered, the old one dropped by score, the driver killed before the state was
    saved; seen in the meta-MRSS protocol). Simulated: after a SIGKILL that checkpoint is
    deleted; the resume goes on from the newest one on disk instead of failing."""
    from rl_scan.tuning.checkpoints import recorded_checkpoints

    cmd = [sys.executable, "-m", "rl_scan.cli", "train", "--algo", "ppo", "--preset", "smoke",
           "--total-env-steps", "4000", "--results", str(tmp_path), "--name", "run"]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    tune_dir = tmp_path / "run" / R.TUNE_DIR

    def named_in_state():  # Tune saves its state now and then; it may be half written
        try:
            return recorded_checkpoints(tune_dir) if tune_dir.is_dir() else []
        except (OSError, ValueError, KeyError):
            return []

    deadline = time.time() + 120
    while time.time() < deadline and not any(p.exists() for p in named_in_state()):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    [named] = recorded_checkpoints(tune_dir)
    assert named.exists() and int(named.name.split("_")[1]) < 9, "kill should land mid-run"
    shutil.rmtree(named)
    out = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert f"names {named.name} of {R.TRAIN_TRIAL}, deleted" in " ".join(out.stdout.split())
    # Training goes on from the checkpoint's counters to the budget. The result reported
    # with the last checkpoint before the SIGKILL may never have reached either of Tune's
    # logs (seen in CI): at most that one iteration is missing.
    merged = R.progress_rows(tmp_path / "run")
    iterations = [int(r[R.ITERATION]) for r in merged]
    assert iterations == sorted(set(iterations)) and iterations[-1] == 10
    assert len(set(range(1, 11)) - set(iterations)) <= 1, iterations
    assert [int(float(r[R.ENV_STEPS])) for r in merged] == [400 * k for k in iterations]


def test_an_env_error_after_a_checkpoint_is_survived_by_restoring_it(ray_session, tmp_path):
    """The env raises once in iteration 2 (its 300th step; 200 per iteration), after the
    checkpoint of iteration 1: Tune marks the trial failed and FailureConfig restores that
    checkpoint, so the log goes on at iteration 2 instead of starting again at 1."""
    marker = tmp_path / "crashed"
    run_dir = train("ppo", {"fault_at_step": 300, "fault_once_file": str(marker)}, "smoke",
                    results_dir=tmp_path, preset_overrides={"total_env_steps": 1600})
    assert marker.exists()  # the fault did happen
    trial = R.tune_trial_dir(run_dir)
    assert "injected env fault at step 300" in (trial / "error.txt").read_text()
    rows = _progress(run_dir)
    iters = [int(r["training_iteration"]) for r in rows]
    steps = [int(float(r[R.ENV_STEPS])) for r in rows]
    # a restart from scratch would log iteration 1 (400 env steps) twice
    assert iters == [1, 2, 3, 4] and steps == [400, 800, 1200, 1600]
    evals = json.loads((run_dir / R.EVAL_FILE).read_text())
    assert [e["training_iteration"] for e in evals] == [1, 2, 3, 4]
    # the run's own clock, carried in the checkpoint, is Tune's time across the restore
    assert [e[R.TIME_TOTAL] for e in evals] == pytest.approx(
        [float(r[R.TIME_TOTAL]) for r in rows], abs=1e-6)


def test_a_non_finite_loss_stops_the_run_and_keeps_the_last_good_checkpoint(ray_session,
                                                                           tmp_path):
    """A NaN reward in iteration 2 makes its losses NaN: the run stops with the loss named,
    iteration 2 writes no checkpoint, the kept one (iteration 1) has finite weights, and no
    FailureConfig retry trains again (with the once-file a retry would not meet the NaN
    again and would finish the run)."""
    import torch

    from rl_scan.algorithms.rollout import load_actors

    marker = tmp_path / "nan_given"
    with pytest.raises(RuntimeError, match=r"(?s)training failed: .*\w*loss\w*=nan for module "
                                           r".* at training iteration 2.*not retried"):
        train("ppo", {"fault_at_step": 300, "fault_kind": "nan_reward",
                      "fault_once_file": str(marker)}, "smoke", results_dir=tmp_path,
              name="run", preset_overrides={"total_env_steps": 1600})
    assert marker.exists()
    run_dir = tmp_path / "run"
    assert [int(r["training_iteration"]) for r in _progress(run_dir)] == [1]
    trial = R.tune_trial_dir(run_dir)
    assert "at training iteration 2" in (trial / R.NONFINITE_FILE).read_text()
    checkpoints = sorted(trial.glob("checkpoint_*"))
    assert [c.name for c in checkpoints] == ["checkpoint_000000"]  # iteration 1's
    actors = load_actors(checkpoints[0])
    assert set(actors) == {"wheeled", "quad"}
    for module in actors.values():
        assert all(torch.isfinite(p).all() for p in module.parameters())


def test_the_console_shows_only_rl_scans_own_lines_unless_verbose(tmp_path):
    """What a user sees of `rl-scan train`: our header, progress and done lines; Ray's own
    log lines (timestamped INFO/WARNING records, C++ logs) only with --verbose."""
    import re

    ray_line = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+\s+(INFO|WARNING)|\[\d{4}-)")
    base = [sys.executable, "-m", "rl_scan.cli", "train", "--preset", "smoke",
            "--total-env-steps", "400", "--results", str(tmp_path)]
    env = {**os.environ, "COLUMNS": "200"}
    env.pop("RAY_LOGGER_LEVEL", None)
    quiet = subprocess.run(base + ["--name", "quiet"], capture_output=True, text=True,
                           timeout=300, env=env)
    assert quiet.returncode == 0, quiet.stderr[-2000:]
    lines = (quiet.stdout + quiet.stderr).splitlines()
    assert [line for line in lines if ray_line.match(line)] == []
    assert lines[0].startswith("poca on ablation") and lines[-1].startswith("done: ")
    assert any(re.match(r"quiet +iter +1 +env steps +400", line) for line in lines)
    loud = subprocess.run(base + ["--name", "loud", "--verbose"], capture_output=True,
                          text=True, timeout=300, env=env)
    assert loud.returncode == 0, loud.stderr[-2000:]
    assert any(ray_line.match(line) for line in (loud.stdout + loud.stderr).splitlines())


def test_default_run_names_are_folder_safe():
    from rl_scan.tuning.launch import scenario_label

    assert scenario_label("test:3") == "test3"
    assert scenario_label("train:*") == "train-any"
    assert scenario_label("tests/data/one_box.yaml") == "one_box"
    assert scenario_label("ablation") == "ablation"


def test_a_trial_resumed_before_its_final_checkpoint_finds_it_beside(tmp_path):
    """Tune's saved state may name checkpoint 1 while the trial already wrote its final one
    (the driver was killed within Tune's ~10 s state-save period): that one is reported."""
    from ray import tune

    from rl_scan.tuning.driver import FINAL_RESULT, final_checkpoint

    def write(index: int, steps: int, final: bool) -> Path:
        folder = tmp_path / f"checkpoint_{index:06d}"
        folder.mkdir()
        R.write_json(folder / R.CHECKPOINT_STEPS, {"env_steps": steps, R.ITERATION: index + 1,
                                                   **({FINAL_RESULT: {}} if final else {})})
        return folder

    named = tune.Checkpoint.from_directory(str(write(0, 400, False)))
    write(1, 800, False)
    assert final_checkpoint(named, 1200) is None  # the run has not ended: train on
    last = write(2, 1200, True)
    assert final_checkpoint(named, 1200) == last
    assert final_checkpoint(named, 1600) is None  # a longer budget than it trained to
