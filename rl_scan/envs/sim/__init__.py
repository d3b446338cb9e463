"""The 3D scanning simulator core. Imports no RL library.

Numba's on-disk cache keys a function on its own file only, so a change to a kernel in
another file (e.g. ``dynamics.move_robots``, called from ``world.step_world``) would run
stale machine code. The cache therefore lives in a folder named by a hash of all the
simulator sources, unless the user set NUMBA_CACHE_DIR.
"""

import hashlib
import os
from pathlib import Path


def _kernel_cache_dir() -> str:
    digest = hashlib.sha1()
    for src in sorted(Path(__file__).parent.glob("*.py")):
        digest.update(src.read_bytes())
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return str(base / "rl_scan" / "numba" / digest.hexdigest()[:16])


if not os.environ.get("NUMBA_CACHE_DIR"):
    import numba

    numba.config.CACHE_DIR = _kernel_cache_dir()
