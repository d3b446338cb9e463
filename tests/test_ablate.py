"""Ablation studies: condition mapping, input checks, and a smoke study of 2 trials under
Tune + Optuna (SQLite) that is killed mid-way and resumed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import warnings

import pytest

from rl_scan import results as R
from rl_scan.cli import main
from rl_scan.studies import STUDIES, TrialRun
from rl_scan.tuning.ablate import only_conditions, resumable_optuna_search, search_space
from rl_scan.tuning.driver import RunProgress, make_run_spec


def test_conditions_map_to_runs():
    comm = STUDIES["comm"]
    assert len(comm.conditions) == 8  # Table II's seven schemes + no object information
    assert comm.run_of({"condition": "5"}) == TrialRun(
        "poca", {"comm_scheme": 5, "object_info": True})
    assert STUDIES["algo"].run_of({"condition": "ppo"}).algo == "ppo"
    assert STUDIES["team"].run_of({"condition": "0,4"}).env == {
        "team": {"wheeled": 0, "quad": 4}}
    run = STUDIES["hpo"].run_of({"lr": 1e-3, "entropy_coeff": 0.01, "lambda_": 0.9,
                                 "num_epochs": 2.0})
    assert run.algo == "poca" and run.algo_kwargs == {"lr": 1e-3, "entropy_coeff": 0.01,
                                                      "lambda_": 0.9, "num_epochs": 2}


def test_a_trial_keeps_the_users_env_under_its_condition():
    base = make_run_spec("poca", {"scenario": "test:1", "comm_scheme": 4}, "smoke")
    spec = base.for_trial("comm", {"condition": "1-noinfo", "seed": 2})
    assert (spec.env.scenario, spec.env.comm_scheme, spec.env.object_info) == (
        "test:1", 1, False)
    assert spec.env.max_steps == 50  # the smoke preset's env override stays
    assert (spec.algo, spec.seed, spec.study) == ("poca", 2, "comm")
    assert base.for_trial("algo", {"condition": "ppo", "seed": 0}).algo == "ppo"


def test_the_reward_study_crosses_reward_mode_with_the_algorithm():
    study = STUDIES["reward"]
    assert study.run_of({"condition": "poca/team", "seed": 1}) == TrialRun(
        "poca", {"reward_mode": "team"})
    assert study.run_of({"condition": "ppo/individual"}) == TrialRun(
        "ppo", {"reward_mode": "individual"})
    base = make_run_spec("poca", {}, "smoke")
    specs = [base.for_trial("reward", p) for p in study.example_params()]
    assert {(s.algo, s.env.reward_mode) for s in specs} == {
        (a, m) for a in ("poca", "ppo") for m in ("individual", "team")}
    for spec in specs:  # every condition is a valid run
        spec.algorithm_config()
    assert ("poca/team", "poca/individual") in study.report.comparisons
    assert search_space(study, 3)[2] == 12


def test_a_study_can_run_a_subset_of_its_conditions():
    study = only_conditions(STUDIES["reward"], ["ppo/team", "poca/team", "ppo/team"])
    assert study.conditions == ("ppo/team", "poca/team")  # order kept, repeats dropped
    assert search_space(study, 3)[2] == 6
    assert only_conditions(STUDIES["team"], None) is STUDIES["team"]
    # the command line's string; the team study's conditions hold commas themselves
    assert only_conditions(STUDIES["team"], "2,2,0,4").conditions == ("2,2", "0,4")
    assert only_conditions(STUDIES["reward"], "poca/team,ppo/team").conditions == (
        "poca/team", "ppo/team")


@pytest.mark.parametrize("argv, message", [
    (["ablate", "reward", "--conditions", "poca/team,poca/teem"],
     "conditions='poca/teem' is invalid: allowed conditions of reward: poca/individual"),
    (["ablate", "hpo", "--conditions", "x"], "conditions='x' is invalid: allowed none: hpo"),
    (["ablate", "team", "--conditions", "2,2,3,1"],
     "conditions='3,1' is invalid: allowed conditions of team: 2,2; 0,4; 4,0"),
])
def test_unknown_conditions_are_named_before_ray_starts(tmp_path, capsys, argv, message):
    code = main([*argv, "--preset", "smoke", "--results", str(tmp_path)])
    assert code == 2 and message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_the_search_keeps_a_resumed_trials_first_values_and_ignores_it_once_finished(
        tmp_path):
    """A resumed trial repeats the iterations after its checkpoint: Optuna keeps the first
    value of each step, silently; results after Optuna finished the trial are dropped."""
    import optuna
    from optuna.distributions import CategoricalDistribution

    storage = optuna.storages.RDBStorage(f"sqlite:///{tmp_path / 'optuna.db'}")
    searcher = resumable_optuna_search(
        space={"seed": CategoricalDistribution([0, 1])}, metric="score", mode="max",
        study_name="s", storage=storage)
    searcher.suggest("t")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for step, score in [(1, 0.1), (2, 0.2), (2, 0.9), (3, 0.3)]:
            searcher.on_trial_result("t", {"score": score, "training_iteration": step})
    searcher.on_trial_complete("t", {"score": 0.3, "training_iteration": 3})
    searcher.on_trial_result("t", {"score": 0.8, "training_iteration": 4})
    searcher.on_trial_complete("t", {"score": 0.8, "training_iteration": 4})
    (trial,) = optuna.load_study(study_name="s", storage=storage).trials
    assert trial.intermediate_values == {1: 0.1, 2: 0.2, 3: 0.3}
    assert trial.value == 0.3


def test_grid_size_is_conditions_times_seeds():
    assert search_space(STUDIES["comm"], 3)[2] == 24
    assert search_space(STUDIES["team"], 2)[2] == 6
    assert search_space(STUDIES["team"], 2, first_seed=3)[0]["seed"].choices == (3, 4)
    assert search_space(STUDIES["hpo"], 3)[2] is None  # TPE: --trials decides


@pytest.mark.parametrize("argv, message", [
    (["ablate", "algo", "--seeds", "0"], "seeds=0"),
    (["ablate", "hpo", "--trials", "0"], "trials=0"),
    # a run needs 1 + runners CPUs: one more than this machine has
    (["ablate", "comm", "--num-env-runners", str(os.cpu_count())],
     f"num_env_runners={os.cpu_count()} is invalid: allowed at most {os.cpu_count() - 1}"),
])
def test_bad_study_input_fails_before_anything_is_written(tmp_path, capsys, argv, message):
    code = main([*argv, "--preset", "smoke", "--results", str(tmp_path)])
    assert code == 2 and message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
    # the resource check starts Ray to count CPUs; the command must stop what it started
    assert "ray" not in sys.modules or not sys.modules["ray"].is_initialized()


def test_a_study_another_process_is_running_is_refused(tmp_path, capsys, held_elsewhere):
    """Two processes on one study (a second --resume beside the first) would train the
    same trials twice into the same files: the second is refused before it writes."""
    with held_elsewhere(tmp_path, "study"):  # held as a running study holds it
        code = main(["ablate", "algo", "--preset", "smoke", "--results", str(tmp_path),
                     "--name", "study"])
    assert code == 2
    assert ("name='study' is invalid: allowed a study no other process is running"
            in capsys.readouterr().err)
    assert not (tmp_path / "study").exists()
    with R.folder_lock(tmp_path, "study"):  # released with its holder
        pass


def test_a_folder_lock_waits_for_its_holder_then_gives_up(tmp_path, held_elsewhere):
    with held_elsewhere(tmp_path, "run"):
        start = time.monotonic()
        with pytest.raises(R.FolderBusy, match=r"\.run\.lock is held"):
            with R.folder_lock(tmp_path, "run", wait_s=1.5):
                pass
        assert time.monotonic() - start >= 1.5


def test_a_folder_lock_is_re_entrant_in_its_thread_only(tmp_path):
    """The job runner holds a run's lock around ``launch.train``, which takes it again:
    the same thread goes through, any other holder (thread or process) is refused."""
    import threading

    refused = []

    def other_thread():
        try:
            with R.folder_lock(tmp_path, "run"):
                refused.append(False)
        except R.FolderBusy:
            refused.append(True)

    with R.folder_lock(tmp_path, "run"):
        with R.folder_lock(tmp_path, "run"):  # nested: no wait on itself
            thread = threading.Thread(target=other_thread)
            thread.start()
            thread.join()
        thread = threading.Thread(target=other_thread)  # the outer hold still counts
        thread.start()
        thread.join()
    assert refused == [True, True]
    other_thread()  # released with its outer holder
    assert refused == [True, True, False]

@pytest.mark.slow
def test_smoke_study_is_killed_and_resumed_to_completion(tmp_path):
    import optuna

    cmd = [sys.executable, "-m", "rl_scan.cli", "ablate", "algo", "--preset", "smoke",
           "--seeds", "1", "--total-env-steps", "2400", "--results", str(tmp_path),
           "--name", "study"]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    tune_dir = tmp_path / "study" / R.TUNE_DIR
    deadline = time.time() + 180
    while time.time() < deadline and len(list(tune_dir.glob("*/checkpoint_*"))) < 3:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    # env steps both trials had evaluated at the kill (our own files: Tune's progress.csv
    # is flushed later): less than 2 x 2400 if the kill landed mid-study
    logged = sum(max((e["env_steps"] for e in R.read_json(run / R.EVAL_FILE) or []),
                     default=0) for run in (tmp_path / "study" / R.TRIALS_DIR).iterdir())
    assert 0 < logged < 2 * 2400, "kill should land mid-study"
    out = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=400)
    assert out.returncode == 0, out.stderr[-2000:]
    study = optuna.load_study(study_name="study",
                              storage=f"sqlite:///{tmp_path / 'study' / 'optuna.db'}")
    done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    assert sorted(t.params["condition"] for t in done) == ["poca", "ppo"]
    runs = sorted((tmp_path / "study" / R.TRIALS_DIR).iterdir())
    assert len(runs) == 2
    for run in runs:
        with open(R.tune_trial_dir(run) / R.RESULT_FILE) as f:  # every result, repeats too
            steps = [int(json.loads(line)[R.ENV_STEPS]) for line in f if line.strip()]
        # a restart from scratch would log 400, 800, ... again after the kill
        assert steps == sorted(set(steps)) and steps[-1] == 2400
        evals = json.loads((run / R.EVAL_FILE).read_text())
        iters = [e["training_iteration"] for e in evals]
        assert iters == sorted(set(iters)) and evals[-1]["env_steps"] == 2400
        condition = R.read_yaml(run / R.RUN_FILE)["params"]["condition"]
        value = next(t.value for t in done if t.params["condition"] == condition)
        assert value == pytest.approx(evals[-1]["coverage"])  # Optuna got the final score


def test_the_finished_count_includes_trials_a_resume_restored_as_done(capsys):
    from ray.tune.experiment import Trial

    trials = [Trial("t", config={"condition": c, "seed": 0}, stub=True)
              for c in ("2,2", "0,4", "4,0")]
    trials[0].set_status(Trial.TERMINATED)  # finished before the driver was killed
    progress = RunProgress(1000, study="team", trials=3)
    progress.on_trial_complete(0, trials, trials[2])
    assert capsys.readouterr().out.startswith("finished 2/3: condition=4,0, seed=0")


def test_the_time_left_is_the_env_steps_left_at_the_trials_pace(capsys):
    """By hand: 4 trials of 1,000 env steps, 2 at a time. One finished (1,000 steps in
    100 s) and one half way (500 in 50 s): 1,500 steps in 150 s, 10 per s per trial;
    2,500 left / 10 / 2 = 125 s (2 min)."""
    from ray.tune.experiment import Trial

    trials = [Trial("t", config={"condition": c, "seed": 0}, stub=True)
              for c in ("2,2", "0,4")]
    for trial, (steps, seconds) in zip(trials, [(1000, 100.0), (500, 50.0)]):
        trial.update_last_result({R.ENV_STEPS: steps, "time_total_s": seconds})
    progress = RunProgress(1000, study="team", trials=4, concurrent=2)
    progress.on_trial_complete(0, trials, trials[0])
    assert capsys.readouterr().out == ("finished 1/4: condition=2,2, seed=0 eval coverage "
                                       "nan; about 2 min left\n")
    del progress.concurrent  # a callback pickled by a study from before this estimate
    progress.on_trial_complete(0, trials, trials[0])
    assert capsys.readouterr().out.endswith("; about 4 min left\n")
