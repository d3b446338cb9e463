"""The runner of many resumable runs (``rl_scan.tuning.jobs``): skipping finished runs,
waiting for prerequisites and for a run another process still writes, failures, what it
says about the time left, and a run that outlives its killed driver."""

from __future__ import annotations

import io
import sys
from pathlib import Path

import pytest
from rich.console import Console

from rl_scan import results as R
from rl_scan.config import ConfigError
from rl_scan.tuning.jobs import Job, Progress, run_jobs


class FakeJob(Job):
    """A job that records when it ran instead of training."""

    def __init__(self, name, log, after=None, action=None, done=False):
        super().__init__(name, None, name, {}, after)
        self.log, self.action, self.done = log, action, done

    @property
    def finished(self):
        return self.done

    def run(self, child=False, address=None):
        self.log.append(("start", self.name))
        if self.action:
            self.action()
        self.log.append(("end", self.name))


def test_a_finished_run_is_skipped_when_the_experiment_is_re_run(tmp_path):
    """A run folder with DONE is returned as it is: no training is started (this job's
    algorithm does not exist, so starting one would raise)."""
    done = tmp_path / "poca_test0_s0"
    done.mkdir()
    (done / R.DONE).write_text("finished\n")
    (done / R.EVAL_FILE).write_text("[]")
    job = Job("poca test:0 s0", tmp_path, done.name, {"algo": "no-such-algo", "env_config": {}})
    assert job.run() == done and (done / R.EVAL_FILE).read_text() == "[]"
    with pytest.raises(ConfigError, match="no-such-algo"):  # the same job, not finished
        Job("poca test:1 s0", tmp_path, "poca_test1_s0",
            {"algo": "no-such-algo", "env_config": {}}).run()


def test_a_re_run_waits_for_a_run_still_being_written_by_another_process(tmp_path):
    """A killed experiment's run may still be stopping when the command is run again: the
    new process waits for its lock and, finding the run finished, starts nothing."""
    import subprocess
    import sys
    import time

    holder = subprocess.Popen([sys.executable, "-c", (
        "import fcntl, pathlib, sys, time\n"
        f"root = pathlib.Path({str(tmp_path)!r})\n"
        "f = open(root / '.poca_test0_s0.lock', 'a+'); fcntl.flock(f, fcntl.LOCK_EX)\n"
        "print('locked', flush=True); time.sleep(2)\n"
        "(root / 'poca_test0_s0').mkdir(); (root / 'poca_test0_s0' / 'DONE').write_text('x')\n")],
        stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    start = time.monotonic()
    job = Job("poca test:0 s0", tmp_path, "poca_test0_s0",
              {"algo": "no-such-algo", "env_config": {}})  # training would raise
    assert job.run() == tmp_path / "poca_test0_s0"
    assert time.monotonic() - start > 1.0  # it waited for the other process
    holder.wait()


def test_jobs_run_in_parallel_and_wait_for_their_prerequisite():
    import threading

    from rich.console import Console

    log, both = [], threading.Barrier(2, timeout=30)
    pre = FakeJob("pre", log, action=both.wait)  # pre and free must overlap, or time out
    jobs = [pre, FakeJob("adapt", log, after=pre), FakeJob("free", log, action=both.wait)]
    run_jobs(jobs, workers=2, console=Console(quiet=True))
    assert log.index(("end", "pre")) < log.index(("start", "adapt"))
    assert sorted(log) == sorted([(e, n) for n in ("pre", "adapt", "free")
                                  for e in ("start", "end")])


def test_after_a_failure_no_new_job_starts_and_the_error_is_raised():
    import threading
    import time

    from rich.console import Console

    failing = threading.Event()

    def boom():
        failing.set()
        raise RuntimeError("env crashed")

    def after_boom():  # still running when the failure is seen
        failing.wait(30)
        time.sleep(0.3)

    log = []
    pre = FakeJob("pre", log, action=boom)
    jobs = [pre, FakeJob("adapt", log, after=pre), FakeJob("other", log, action=after_boom),
            FakeJob("later", log)]
    with pytest.raises(RuntimeError, match="env crashed"):
        run_jobs(jobs, workers=2, console=Console(quiet=True))
    started = {n for e, n in log if e == "start"}
    assert started == {"pre", "other"}
    assert ("end", "other") in log  # the running job was let finish


def _exited(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal")
def test_a_run_whose_driver_died_exits_even_when_its_graceful_stop_hangs(tmp_path):
    """The driver is SIGKILLed; its run child ignores the SIGINT (a hung Tune stop) and must
    still exit once the grace period is over, its threads' stacks in its log."""
    import subprocess
    import time

    child = ("import os, signal, sys, time; import rl_scan.tuning.jobs as J; "
             "J.STOP_GRACE_S = 1.0; signal.signal(signal.SIGINT, signal.SIG_IGN); "
             "J._stop_with_parent(int(sys.argv[1])); print(os.getpid(), flush=True); "
             "time.sleep(120)")
    log = tmp_path / "run.log"
    driver = subprocess.Popen(["bash", "-c", f'"{sys.executable}" -c "$1" $$ 2>"{log}"; :',
                               "bash", child], stdout=subprocess.PIPE, text=True)
    pid = int(driver.stdout.readline())
    driver.kill()
    driver.wait()
    killed = time.monotonic()
    while not _exited(pid) and time.monotonic() - killed < 30:
        time.sleep(0.1)
    assert _exited(pid), "the run outlived its driver by 30 s"
    assert time.monotonic() - killed >= 1.0  # it was given the grace period
    text = log.read_text()
    assert "did not stop within 1 s; exiting" in text
    assert "most recent call first" in text and 'File "<string>", line 1' in text  # main


def test_finished_runs_are_skipped_and_their_dependents_start():
    """A re-run starts no finished run (not even a child process to find it done) and
    lets the runs that waited for it start."""
    log = []
    pre = FakeJob("pre", log, done=True)
    jobs = [pre, FakeJob("adapt", log, after=pre), FakeJob("other", log)]
    out = io.StringIO()
    run_jobs(jobs, workers=2, console=Console(file=out, width=200))
    assert sorted(n for e, n in log if e == "start") == ["adapt", "other"]
    text = out.getvalue()
    assert "1 of 3 runs already finished (skipped)" in text
    assert "run 2/3: adapt" in text and "run 3/3: other" in text  # places in the plan
    assert "run 1/3" not in text


def test_time_left_is_the_budget_left_at_the_pace_of_runs_finished_from_scratch(tmp_path):
    """By hand, 2 runs at a time, 36,000 env steps each: b finishes after 3,600 s (10 env
    steps/s per run, 20 for both), leaving c and d: 72,000 / 20 = 60 min. d was resumed, so
    its time says nothing about the pace: after it, 36,000 / 20 = 30 min."""
    jobs = [Job(n, tmp_path, n, {}, env_steps=36_000) for n in "abcd"]
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / R.DONE).write_text("finished\n")
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / R.RUN_FILE).write_text("algo: poca\n")
    now = [0.0]
    out = io.StringIO()
    progress = Progress(jobs, workers=2, console=Console(file=out, width=200),
                        clock=lambda: now[0])
    a, b, c, d = jobs
    progress.start(b)
    progress.start(c)
    now[0] = 3600.0
    progress.end(b)
    progress.start(d)
    now[0] = 5400.0
    progress.end(d)
    now[0] = 7200.0
    progress.end(c)
    lines = out.getvalue().splitlines()
    assert lines == [
        "1 of 4 runs already finished (skipped)",
        "run 2/4: b", "run 3/4: c",
        "finished b in 60 min (2/4 runs done; about 60 min left at this session's pace)",
        "run 4/4: d (resuming)",
        "finished d in 30 min (3/4 runs done; about 30 min left at this session's pace)",
        "finished c in 2.0 h (4/4 runs done)"]
