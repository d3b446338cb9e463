"""Own random streams for MetaPOCA's task work, so that theta's own work draws DR's numbers.

Everything in a local-mode run (the runner's action noise, RLlib's and POCA's minibatch
shuffles) draws from the process's global Python, numpy and torch generators. A
meta-iteration's task work (inner updates, query sampling, the MAML term) drawing from
them too would shift every later number theta's sampling and update draw: with no MAML
term the run would be DR in law but not in fact, and a comparison with DR could not pair
the two. Inside ``own_random_streams`` the task work draws from generators seeded from its
own key, and the global ones come back as they were.
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import torch


@contextmanager
def own_random_streams(*key: int) -> Iterator[None]:
    """Python's, numpy's and torch's global generators seeded from ``key`` (e.g. seed,
    iteration, phase, task) inside the block, and as they were before it afterwards."""
    saved = random.getstate(), np.random.get_state(), torch.get_rng_state()
    seed = int(np.random.SeedSequence([int(k) for k in key]).generate_state(1)[0])
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    try:
        yield
    finally:
        random.setstate(saved[0])
        np.random.set_state(saved[1])
        torch.set_rng_state(saved[2])
