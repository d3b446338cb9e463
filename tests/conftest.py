"""Shared fixtures. Ray is started at most once per test run, and only if a test asks."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def ray_session():
    """One local Ray for the whole run (2 CPUs, no dashboard), as RLlib tests need."""
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()
