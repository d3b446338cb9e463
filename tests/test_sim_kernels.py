"""Shape of the simulator code: kernels take records, not long positional argument lists.

Issue 12 replaced kernels of 13-41 positional arguments by a few records; these checks
keep new arguments going into a record instead of back onto a signature.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import rl_scan.envs.core as core
import rl_scan.envs.sim as sim

MAX_PARAMETERS = 12
MAX_LINES = 400
SOURCES = sorted(Path(sim.__file__).parent.glob("*.py")) + [Path(core.__file__)]


def _parameters(fn: ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda) -> int:
    a = fn.args
    return (len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None)
            + (a.kwarg is not None))


@pytest.mark.parametrize("source", SOURCES, ids=lambda p: p.name)
def test_no_function_takes_more_than_twelve_parameters(source):
    tree = ast.parse(source.read_text())
    long = {getattr(fn, "name", "<lambda>"): _parameters(fn) for fn in ast.walk(tree)
            if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
            and _parameters(fn) > MAX_PARAMETERS}
    assert not long, f"group arguments into a record (see sim/world.py): {long}"


@pytest.mark.parametrize("source", SOURCES, ids=lambda p: p.name)
def test_no_file_is_longer_than_four_hundred_lines(source):
    assert len(source.read_text().splitlines()) <= MAX_LINES
