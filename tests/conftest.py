"""Shared fixtures. Ray is started at most once per test run, and only if a test asks."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--window-size=1100,800", "--virtual-time-budget=8000"]


class Chromium:
    """Headless Chromium (WebGL through SwiftShader): the DOM after scripts ran, screenshots."""

    def __init__(self, profile: Path):
        self.common = [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}"]

    def dom(self, page: Path) -> str:
        return subprocess.run([*self.common, "--dump-dom", page.as_uri()], capture_output=True,
                              text=True, timeout=120).stdout

    def screenshot(self, page: Path, out: Path):
        """The rendered page as an (N, 3) int array of RGB pixels."""
        import numpy as np
        from PIL import Image

        subprocess.run([*self.common, f"--screenshot={out}", page.as_uri()],
                       capture_output=True, timeout=120, check=True)
        return np.asarray(Image.open(out).convert("RGB")).reshape(-1, 3).astype(int)


@pytest.fixture
def chromium(tmp_path):
    """Skipped where Chromium is missing, except in CI (``.ci/run`` installs it)."""
    if CHROMIUM is None:
        if os.environ.get("CI"):
            pytest.fail("CI must have chromium (see .ci/run)")
        pytest.skip("headless Chromium not installed (CI installs it)")
    return Chromium(tmp_path / "chromium-profile")


@pytest.fixture(scope="session")
def ray_session():
    """One local Ray for the whole run (2 CPUs, no dashboard), as RLlib tests need."""
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture
def held_elsewhere():
    """``held_elsewhere(parent, name)``: a context in which another thread holds
    ``results.folder_lock(parent, name)``, as a second process running that run or study
    would (the lock is re-entrant in its own thread only)."""
    import threading
    from contextlib import contextmanager

    from rl_scan import results as R

    @contextmanager
    def hold(parent: Path, name: str):
        taken, release = threading.Event(), threading.Event()

        def holder():
            with R.folder_lock(parent, name):
                taken.set()
                release.wait(60)

        thread = threading.Thread(target=holder)
        thread.start()
        assert taken.wait(10), "the holder thread could not take the lock"
        try:
            yield
        finally:
            release.set()
            thread.join()

    return hold
