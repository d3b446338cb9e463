"""Many training runs, resumable and side by side (the meta-MRSS protocol's runner).

A ``Job`` is one ``launch.train`` run that is skipped once finished (a ``DONE`` file) and
resumed if interrupted; ``run_jobs`` runs a list of them in order, several at a time,
each after the job it waits for, and says how much is left (``Progress``). Concurrent runs
are child processes (see ``run_jobs`` for why), each logging its stderr to ``logs/``
beside its run folder.
"""

from __future__ import annotations

import faulthandler
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rl_scan.config import RunInterrupted
from rl_scan.results import DONE, LOG_DIR, RUN_FILE, FolderBusy, folder_lock
from rl_scan.tuning.driver import format_duration
from rl_scan.tuning.launch import train


def _run(folder: Path, name: str, **kwargs) -> Path:
    """Train unless finished; resume if interrupted. One process at a time per run: a
    re-run waits for a run still stopping (e.g. one whose experiment driver was killed)."""
    run_dir = folder / name
    if (run_dir / DONE).is_file():
        return run_dir
    with _run_lock(folder, name):
        if (run_dir / DONE).is_file():  # finished while we waited
            return run_dir
        resume = (run_dir / RUN_FILE).is_file()
        train(results_dir=folder, name=name, resume=resume, **kwargs)
        (run_dir / DONE).write_text("finished\n")
    return run_dir


LOCK_WAIT_S = 300.0


@contextmanager
def _run_lock(folder: Path, name: str):
    """The run's folder lock (``results.folder_lock``), waiting for a run still stopping."""
    try:
        with folder_lock(folder, name, LOCK_WAIT_S):
            yield
    except FolderBusy:
        raise RuntimeError(f"run {name} in {folder} is still being written by another "
                           f"process after {LOCK_WAIT_S:.0f} s") from None


@dataclass(eq=False)
class Job:
    """One training run; it may start once ``after`` has finished."""

    label: str
    folder: Path
    name: str
    kwargs: dict[str, Any]
    after: Job | None = None
    env_steps: int = 0
    """The run's budget: it weighs the run in the time-left estimate (0: not counted)."""

    @property
    def finished(self) -> bool:
        return (self.folder / self.name / DONE).is_file()

    def run(self, child: bool = False, address: str | None = None) -> Path:
        """Train in this process, or in a child process: on the Ray cluster at
        ``address``, or else on a local Ray of its own (see ``run_jobs``)."""
        if not child:
            return _run(self.folder, self.name, address=address, **self.kwargs)
        spec = {"folder": str(self.folder), "name": self.name, "address": address,
                **self.kwargs, "init_from": _str_or_none(self.kwargs.get("init_from"))}
        log = self.folder.parent / LOG_DIR / f"{self.folder.name}_{self.name}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "ab") as err:  # stdout (progress lines) goes to the terminal
            proc = subprocess.Popen([sys.executable, "-c", _CHILD,
                                     json.dumps({**spec, "parent_pid": os.getpid()})],
                                    stderr=err, start_new_session=True)
            with _CHILDREN_LOCK:
                _CHILDREN.add(proc)
            try:
                code = proc.wait()
            finally:
                with _CHILDREN_LOCK:
                    _CHILDREN.discard(proc)
        if code != 0:
            tail = log.read_text(errors="replace").strip().splitlines()[-5:]
            raise RuntimeError(f"{self.name} exited with code {code}; from {log}:\n"
                               + "\n".join(tail))
        return self.folder / self.name


LAUNCH_GAP_S = 2.0  # between child runs on a shared cluster (see run_jobs)
_CHILD = ("import sys; from rl_scan.tuning.jobs import child_main; "
          "sys.exit(child_main(sys.argv[1]))")
_CHILDREN: set[subprocess.Popen] = set()
_CHILDREN_LOCK = threading.Lock()


def _str_or_none(value: Any) -> str | None:
    return None if value is None else str(value)


STOP_GRACE_S = 60.0  # a run whose driver died must stop within this (see _stop_with_parent)


def _stop_with_parent(parent_pid: int) -> None:
    """SIGINT this process when its parent dies (Linux), so a killed driver's runs stop as
    after Ctrl+C (Tune keeps their state) instead of running on unowned. Tune's graceful
    stop can wait on a cluster that lost a node; nobody is left to press Ctrl+C twice, so
    a watchdog exits ``STOP_GRACE_S`` after the parent's death, writing every thread's
    stack to the run's log first (resuming works as after a SIGKILL)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None).prctl(1, signal.SIGINT)  # PR_SET_PDEATHSIG
    if os.getppid() != parent_pid:  # it died before the line above
        raise KeyboardInterrupt

    def watchdog() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        time.sleep(STOP_GRACE_S)
        print(f"the driver (pid {parent_pid}) died and this run did not stop within "
              f"{STOP_GRACE_S:.0f} s; exiting. Its threads:", file=sys.stderr, flush=True)
        faulthandler.dump_traceback(all_threads=True)
        os._exit(130)

    threading.Thread(target=watchdog, name="stop-with-parent", daemon=True).start()


def child_main(spec_json: str) -> int:
    """Entry point of a run in a child process (``Job.run`` with an address)."""
    # Ctrl+C (from the parent, or its death) must interrupt even where the shell that
    # started us ignores SIGINT (background jobs of a non-interactive shell).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    spec = json.loads(spec_json)
    try:
        _stop_with_parent(spec.pop("parent_pid"))
        _run(Path(spec.pop("folder")), spec.pop("name"), **spec)
    except RunInterrupted as e:
        print(f"interrupted: {e}", file=sys.stderr)  # the parent says how to resume
        return 130
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return 0


class Progress:
    """The lines ``run_jobs`` prints: runs already finished (skipped), each start (its
    place in the plan, stable across re-runs) and each end, with the time left at this
    session's pace: env steps still to run / env steps per second per run (runs finished
    in this session from scratch; resumed ones had done part of their budget before)
    / runs at a time. Runs still going count in full, so it errs long by up to a run."""

    def __init__(self, jobs: list[Job], workers: int, console, clock=time.monotonic) -> None:
        self.plan, self.workers, self.console, self.clock = jobs, workers, console, clock
        self.done = {job for job in jobs if job.finished}
        self.steps_left = sum(job.env_steps for job in jobs if job not in self.done)
        self.paced_steps, self.paced_seconds = 0, 0.0
        self.began: dict[Job, tuple[float, bool]] = {}  # start time, resumed
        if self.done:
            console.print(f"{len(self.done)} of {len(jobs)} runs already finished "
                          "(skipped)")

    def start(self, job: Job) -> None:
        resumed = job.folder is not None and (job.folder / job.name / RUN_FILE).is_file()
        self.began[job] = (self.clock(), resumed)
        self.console.print(f"[bold]run {self.plan.index(job) + 1}/{len(self.plan)}[/]: "
                           f"{job.label}" + (" (resuming)" if resumed else ""))

    def end(self, job: Job) -> None:
        began, resumed = self.began.pop(job)
        seconds = self.clock() - began
        self.done.add(job)
        self.steps_left -= job.env_steps
        if not resumed and job.env_steps:
            self.paced_steps += job.env_steps
            self.paced_seconds += seconds
        left = ""
        if self.paced_steps and self.steps_left > 0:
            rate = self.paced_steps / self.paced_seconds * self.workers
            left = f"; about {format_duration(self.steps_left / rate)} left at this session's pace"
        self.console.print(f"finished {job.name} in {format_duration(seconds)} "
                           f"({len(self.done)}/{len(self.plan)} runs done{left})")


def run_jobs(jobs: list[Job], workers: int, console, address: str | None = None) -> None:
    """Run ``jobs`` in list order, ``workers`` at a time, each as soon as its
    prerequisite has finished; finished ones (a ``DONE`` file) are skipped. After a
    failure no new job starts; the running ones finish and the first error is raised.

    One worker runs the jobs in this process. More run each job in a child process,
    because two Tune runs must not share a driver process (Tune's trainable registry is
    not thread-safe) nor, locally, a Ray session (runs starting in the same second with
    the same experiment name share one staging folder, which Tune then syncs into both
    run folders). A child joins the cluster at ``address`` if given (launches are
    spaced ``LAUNCH_GAP_S`` apart for this reason), else starts a local Ray of its own.
    Ctrl+C is passed on to the children, which stop at once (Tune keeps their state):
    running the protocol again resumes them.
    """
    progress = Progress(jobs, workers, console)
    waiting = [job for job in jobs if job not in progress.done]
    if workers == 1:  # in this thread, so Tune's own Ctrl+C handling applies
        for job in waiting:
            progress.start(job)
            job.run(address=address)
            progress.end(job)
        return
    running = {}
    failure: BaseException | None = None
    last_launch = -math.inf
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="protocol") as pool:
        try:
            while running or (waiting and failure is None):
                ready = [j for j in waiting if j.after is None or j.after in progress.done]
                for job in ready[:workers - len(running)] if failure is None else []:
                    waiting.remove(job)
                    progress.start(job)
                    if address is not None:
                        time.sleep(max(0.0, last_launch + LAUNCH_GAP_S - time.monotonic()))
                        last_launch = time.monotonic()
                    running[pool.submit(job.run, True, address)] = job
                if not running:  # nothing can start: a prerequisite failed
                    break
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in done:
                    job, error = running.pop(future), future.exception()
                    if error is None:
                        progress.end(job)  # marks it done: its dependents may start
                    else:
                        failure = failure or error
                        console.print(f"[red]{job.name} failed[/]: {error}")
        except KeyboardInterrupt:
            console.print("[red]interrupted[/]: stopping the running runs; run the same "
                          "command again to resume them")
            with _CHILDREN_LOCK:
                for proc in _CHILDREN:
                    proc.send_signal(signal.SIGINT)
            raise
    if failure is not None:
        raise failure
