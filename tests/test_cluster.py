"""A real 2-node Ray cluster on this machine (``ray start`` twice, token authentication as
Ray 2.60 documents it: ``RAY_AUTH_MODE=token`` and a shared ``RAY_AUTH_TOKEN_PATH``).

Each node offers one ``trial_slot`` and runs ask for one (``--trial-resources``), so the
first trials land on both nodes. Mid-study the worker node's raylet is killed with SIGKILL
(its trial fails and FailureConfig restores it on the head), then the driver is killed
with SIGKILL, and the same command is run again: every planned trial ends DONE once.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from rl_scan import results as R
from rl_scan.tuning.jobs import STOP_GRACE_S

pytestmark = [pytest.mark.cluster, pytest.mark.slow]  # minutes each: `pytest -m slow`
RAY = str(Path(sys.executable).parent / "ray")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _processes_under(root: Path) -> dict[int, list[str]]:
    """pid -> argv of every process whose command line names ``root``."""
    out = {}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        args = [a.decode(errors="replace") for a in argv if a]
        if any(str(root) in a for a in args):
            out[int(pid)] = args
    return out


class TwoNodes:
    """Head + worker node started with ``ray start``; ``kill_worker`` SIGKILLs the worker's
    raylet. Only processes under this cluster's temp dir are touched (``ray stop`` would
    stop every Ray on the machine)."""

    def __init__(self) -> None:
        # short: Ray's Unix socket paths (under the temp dir) must stay under 108 bytes
        self.root = Path(tempfile.mkdtemp(prefix="rlc", dir="/tmp"))
        token = self.root / "auth_token"
        token.write_text(secrets.token_hex(32))
        self.env = {**os.environ, "RAY_AUTH_MODE": "token",
                    "RAY_AUTH_TOKEN_PATH": str(token)}
        self.env.pop("RAY_ADDRESS", None)
        port = _free_port()
        self.address = f"127.0.0.1:{port}"
        slot = json.dumps({"trial_slot": 1})
        self._ray("start", "--head", "--port", str(port), "--num-cpus", "2",
                  "--resources", slot, "--temp-dir", str(self.root / "ray"),
                  "--include-dashboard", "false", "--dashboard-port", str(_free_port()),
                  "--disable-usage-stats")
        self.head_id = self._raylets()[0][1]
        self._ray("start", "--address", self.address, "--num-cpus", "2", "--resources", slot,
                  "--disable-usage-stats")
        deadline = time.time() + 60
        while time.time() < deadline and len(self._raylets()) < 2:
            time.sleep(0.5)
        (self.worker_pid, self.worker_id), = [r for r in self._raylets()
                                               if r[1] != self.head_id]

    def _ray(self, *args: str) -> None:
        out = subprocess.run([RAY, *args], env=self.env, capture_output=True, text=True,
                             timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]

    def _raylets(self) -> list[tuple[int, str]]:
        """(pid, node id) of this cluster's raylets, oldest first."""
        found = []
        for pid, args in sorted(_processes_under(self.root).items()):
            if args[0].endswith("/raylet"):
                found += [(pid, a.split("=", 1)[1]) for a in args if a.startswith("--node_id=")]
        return found

    def kill_worker(self) -> None:
        os.kill(self.worker_pid, signal.SIGKILL)

    def teardown(self) -> None:
        for pid in _processes_under(self.root):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        shutil.rmtree(self.root, ignore_errors=True)


@pytest.fixture
def cluster():
    nodes = TwoNodes()
    try:
        yield nodes
    finally:
        nodes.teardown()


def _trial_nodes(run: Path) -> list[str]:
    """The node ids a study trial's training process ran on, in order (nodes.json)."""
    entries = R.read_json(run / R.NODES_FILE) or []
    return [e["trainable"]["node_id"] for e in entries]


def _wait(condition, timeout: float, what: str) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if condition():
            return
        time.sleep(0.5)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _complete(db: Path) -> list:
    import optuna

    if not db.is_file():
        return []
    try:
        study = optuna.load_study(study_name="study", storage=f"sqlite:///{db}")
    except KeyError:  # not created yet
        return []
    return [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]


def test_a_run_too_big_for_the_cluster_is_one_line_within_seconds(cluster, tmp_path):
    """4 CPUs in all: a run of 1 + 4 env runners could never start (Tune would leave it
    PENDING); a custom resource no node has, likewise."""
    base = [sys.executable, "-m", "rl_scan.cli", "train", "--preset", "smoke", "--address",
            cluster.address, "--results", str(tmp_path)]
    for extra, needle in ((["--num-env-runners", "4"],
                           "num_env_runners=4 is invalid: allowed at most 3 on this Ray "
                           "cluster (4 CPUs; a run needs learner_cpus + num_env_runners = 5)"),
                          (["--trial-resources", "trial_slot=2"],
                           "allowed resources one node of this Ray cluster has (trial_slot: "
                           "at most 1 on a node")):
        start = time.monotonic()
        out = subprocess.run(base + extra, env=cluster.env, capture_output=True, text=True,
                             timeout=120)
        assert out.returncode == 2 and time.monotonic() - start < 30
        assert needle in out.stderr and out.stdout == ""
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert not any(tmp_path.iterdir())


def test_a_study_survives_losing_a_node_and_its_driver(cluster, tmp_path):
    started = time.monotonic()
    steps = 3200  # 8 iterations of the smoke preset per trial
    cmd = [sys.executable, "-m", "rl_scan.cli", "ablate", "algo", "--preset", "smoke",
           "--seeds", "2", "--total-env-steps", str(steps), "--trial-resources",
           "trial_slot=1", "--address", cluster.address, "--results", str(tmp_path),
           "--name", "study"]
    study = tmp_path / "study"
    log = open(tmp_path / "driver.log", "w")
    driver = subprocess.Popen(cmd, env=cluster.env, stdout=log, stderr=subprocess.STDOUT,
                              start_new_session=True)

    def runs() -> list[Path]:
        trials = study / R.TRIALS_DIR
        return sorted(trials.iterdir()) if trials.is_dir() else []

    def evals(run: Path) -> list[dict]:
        """Our evaluation file (written at each result; Tune's progress.csv is flushed
        later and may lose its last rows when the driver is SIGKILLed)."""
        return R.read_json(run / R.EVAL_FILE) or []

    def on_worker_with_a_checkpoint() -> Path | None:
        return next((r for r in runs() if cluster.worker_id in _trial_nodes(r)
                     and len(evals(r)) >= 2), None)

    def first_nodes() -> dict[str, str]:
        return {run.name: nodes[0] for run in runs() if (nodes := _trial_nodes(run))}

    _wait(lambda: on_worker_with_a_checkpoint() is not None and set(
        first_nodes().values()) == {cluster.head_id, cluster.worker_id}, 240,
          "trials on both nodes, the worker's past its first checkpoint")
    first = first_nodes()
    lost = on_worker_with_a_checkpoint()
    cluster.kill_worker()
    killed_at = time.monotonic() - started

    db = study / R.OPTUNA_DB
    _wait(lambda: len(_complete(db)) >= 1, 300, "a finished trial after the node loss")
    os.killpg(driver.pid, signal.SIGKILL)
    driver.wait()
    finished_before = {t.number: t.params for t in _complete(db)}
    assert 1 <= len(finished_before) < 4, "the driver kill should land mid-study"
    before = {run.name: evals(run) for run in runs()}

    again = subprocess.run(cmd + ["--resume"], env=cluster.env, capture_output=True,
                           text=True, timeout=600)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    done = _complete(db)
    import optuna

    all_trials = optuna.load_study(study_name="study", storage=f"sqlite:///{db}").trials
    assert len(all_trials) == len(done) == 4  # each planned trial once, all complete
    assert sorted((t.params["condition"], t.params["seed"]) for t in done) == [
        ("poca", 0), ("poca", 1), ("ppo", 0), ("ppo", 1)]
    assert len(runs()) == 4
    for run in runs():  # every iteration evaluated once, none missing, to the budget
        assert [e[R.ITERATION] for e in evals(run)] == list(range(1, 9)), run.name
        assert evals(run)[-1]["env_steps"] == steps
    # the trial on the lost node was restored from its checkpoint onto the head
    assert _trial_nodes(lost)[0] == cluster.worker_id
    assert _trial_nodes(lost)[-1] == cluster.head_id
    # trials finished before the driver was killed were not trained again (Tune's saved
    # state may name an earlier checkpoint: the final one beside it is reported again),
    # and the study's value is the run's last evaluation
    values = {tuple(sorted(t.params.items())): t.value for t in done}
    for run in runs():
        params = R.read_yaml(run / R.RUN_FILE)["params"]
        if params in finished_before.values():
            assert evals(run) == before[run.name], run.name
        assert values[tuple(sorted(params.items()))] == pytest.approx(evals(run)[-1]["coverage"])
    per_node = {node: sum(first_node == node for first_node in first.values())
                for node in (cluster.head_id, cluster.worker_id)}
    print(f"\ncluster study: first placement head {per_node[cluster.head_id]} / worker "
          f"{per_node[cluster.worker_id]} trials; worker raylet killed at {killed_at:.0f} s "
          f"({lost.name} restored on the head: nodes {len(_trial_nodes(lost))} entries); "
          f"driver killed with {len(finished_before)}/4 trials complete; after --resume "
          f"{len(done)}/4 complete, {len(all_trials)} in Optuna; wall "
          f"{time.monotonic() - started:.0f} s")


def test_an_experiment_survives_losing_a_node_and_its_driver(cluster, tmp_path):
    """`experiment meta-mrss --jobs 2`: runs are child processes on the cluster. The node
    loss is retried by Tune inside the run; the driver's death stops its children (as
    Ctrl+C would) and the same command completes the rest without repeating a run."""
    started = time.monotonic()
    steps = 2400  # 6 iterations of the smoke preset per run
    cmd = [sys.executable, "-m", "rl_scan.cli", "experiment", "meta-mrss", "--preset",
           "smoke", "--methods", "dr,poca", "--tests", "0", "--seeds", "2", "--jobs", "2",
           "--pretrain-steps", str(steps), "--adapt-steps", str(steps), "--trial-resources",
           "trial_slot=1", "--address", cluster.address, "--results", str(tmp_path),
           "--name", "mm"]
    root = tmp_path / "mm"
    log = open(tmp_path / "driver.log", "w")
    driver = subprocess.Popen(cmd, env=cluster.env, stdout=log, stderr=subprocess.STDOUT,
                              start_new_session=True)

    def runs() -> list[Path]:
        return sorted(p.parent for p in root.glob(f"*/*/{R.RUN_FILE}"))

    def evals(run: Path) -> list[dict]:
        """Our evaluation file, one entry per evaluated iteration (a restore re-runs the
        iterations after its checkpoint, and their new entries replace the old; Tune's
        progress.csv logs both and may lose its last rows to the driver's SIGKILL)."""
        return [e for e in R.read_json(run / R.EVAL_FILE) or [] if e[R.ITERATION] > 0]

    def on_worker_with_a_checkpoint() -> Path | None:
        return next((r for r in runs() if cluster.worker_id in _trial_nodes(r)
                     and len(evals(r)) >= 2), None)

    _wait(lambda: on_worker_with_a_checkpoint() is not None, 240,
          "a run on the worker node past its first checkpoint")
    lost = on_worker_with_a_checkpoint()
    cluster.kill_worker()
    killed_at = time.monotonic() - started
    _wait(lambda: any((r / R.DONE).is_file() for r in runs()), 300, "a finished run")
    os.killpg(driver.pid, signal.SIGKILL)
    driver.wait()
    # its children stop on their own (parent-death signal): as after Ctrl+C (Tune saving
    # their state), or, where Tune's stop hangs, by the watchdog after STOP_GRACE_S
    killed_driver = time.monotonic()
    _wait(lambda: not any("child_main" in " ".join(a) for a in
                          _processes_under(tmp_path).values()), STOP_GRACE_S + 90,
          "the runs to stop")
    stopped_in = time.monotonic() - killed_driver
    hung = [log.name for log in (root / R.LOG_DIR).glob("*.log")
            if "did not stop within" in log.read_text(errors="replace")]
    finished_before = {r.name: evals(r) for r in runs() if (r / R.DONE).is_file()}
    assert 1 <= len(finished_before) < 6, "the driver kill should land mid-experiment"

    again = subprocess.run(cmd, env=cluster.env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    names = sorted(r.name for r in runs())
    assert names == ["dr_s0", "dr_s1", "dr_test0_s0", "dr_test0_s1", "poca_test0_s0",
                     "poca_test0_s1"]
    for run in runs():
        assert (run / R.DONE).is_file()
        iters = [e[R.ITERATION] for e in evals(run)]
        assert iters == list(range(1, 7)), (run.name, iters)  # none missing
        if run.name in finished_before:  # not run again
            assert evals(run) == finished_before[run.name]
    assert _trial_nodes(lost)[0] == cluster.worker_id
    assert _trial_nodes(lost)[-1] == cluster.head_id
    print(f"\ncluster experiment: worker raylet killed at {killed_at:.0f} s ({lost.name} "
          f"restored on the head); driver killed with {len(finished_before)}/6 runs done; "
          f"runs stopped {stopped_in:.0f} s after the driver's death (by the watchdog: "
          f"{hung or 'none'}); after the re-run 6/6 done, none repeated; wall "
          f"{time.monotonic() - started:.0f} s")
