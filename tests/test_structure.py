"""The code's shape: layering a fresh interpreter can see, RLlib keys named once and right,
files and functions small enough to read, and a design document that names real files."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

from rl_scan import results as R

ROOT = Path(__file__).resolve().parent.parent
MAX_FILE_LINES = 400
MAX_PARAMETERS = 12


def _modules_after_import(statement: str) -> set[str]:
    code = f"import sys; {statement}; print(' '.join(sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    return set(out.stdout.split())


def test_the_pettingzoo_adapter_does_not_pull_in_ray():
    modules = _modules_after_import("import rl_scan.envs.parallel_env")
    assert "rl_scan.envs.parallel_env" in modules
    assert "ray" not in modules and "torch" not in modules


def test_the_command_line_parser_starts_without_ray():
    """``rl-scan --help`` stays instant: registries are read without importing Ray."""
    modules = _modules_after_import(
        "from rl_scan.cli.parser import build_parser; build_parser()")
    assert "rl_scan.algorithms.registry" in modules and "rl_scan.studies" in modules
    assert "ray" not in modules and "torch" not in modules


def test_result_keys_are_rllibs_own():
    from ray.rllib.utils import metrics

    assert R.ENV_STEPS == metrics.NUM_ENV_STEPS_SAMPLED_LIFETIME
    assert R.EVALUATION == metrics.EVALUATION_RESULTS
    assert R.ENV_RUNNERS == metrics.ENV_RUNNER_RESULTS
    assert R.EPISODE_RETURN == metrics.EPISODE_RETURN_MEAN
    assert R.MODULE_RETURNS == metrics.EPISODE_MODULE_RETURN_MEAN


def _sources() -> list[Path]:
    return sorted(p for p in (ROOT / "rl_scan").rglob("*.py"))


def test_no_source_file_is_over_the_line_limit():
    long = {str(p.relative_to(ROOT)): n for p in _sources()
            if (n := len(p.read_text().splitlines())) > MAX_FILE_LINES}
    assert not long, f"split these by role (over {MAX_FILE_LINES} lines): {long}"


def test_no_function_takes_more_than_twelve_parameters():
    wide = []
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                count = (len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
                         + (a.vararg is not None) + (a.kwarg is not None))
                if count > MAX_PARAMETERS:
                    wide.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({count})")
    assert not wide, f"group these parameters into records: {wide}"


@pytest.mark.parametrize("doc", ["docs/DESIGN.md", "README.md"])
def test_every_path_a_document_names_exists(doc):
    """Paths in backquotes that look like project files must exist (docs drift otherwise);
    a path into a folder the project does not have (``notes/``) is a citation of a file
    outside the project, which docs must not make."""
    text = (ROOT / doc).read_text()
    tops = ("rl_scan", "tests", "docs", "reports", ".ci", "envs", "algorithms", "tuning",
            "notes", "paper", "tools", "shared")
    named = {p for p in re.findall(r"`([\w.-]+(?:/[\w.*-]+)+/?)`", text)
             if p.split("/")[0] in tops}
    assert named, f"{doc} names no project path"
    missing = sorted(p for p in named if not any(ROOT.glob(p.rstrip("/"))))
    assert not missing, f"{doc} names files that do not exist: {missing}"
