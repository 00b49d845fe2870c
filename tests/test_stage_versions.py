"""A stage's code version covers exactly the sources it runs: its module and the project modules it imports
(``assets_lib.stages.sources``). Adding an unrelated module leaves every version (and so every stored output)
valid; changing a module a stage imports makes that stage, and only the stages that run it, stale."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from assets_lib.stages.registry import STAGES
from assets_lib.stages.sources import module_closure, source_digest

REPO = Path(__file__).resolve().parents[1]
IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc")


def _copy_sources(dst: Path, packages=("assets_lib", "raw_schemas")) -> Path:
    for pkg in packages:
        shutil.copytree(REPO / pkg, dst / pkg, ignore=IGNORE)
    return dst


def _digests(root: Path) -> dict[str, str]:
    return {s.name: source_digest(s.compute.__module__, root) for s in STAGES}


def test_closure_is_what_a_stage_imports():
    rate = module_closure("assets_lib.stages.calibration")
    assert "assets_lib.calibration.rate_fit" in rate and "assets_lib.calibration.segmentation" in rate
    assert "assets_lib.fleet.drift" not in rate and "assets_lib.noise.allan" not in rate
    assert "assets_lib.noise.allan" in module_closure("assets_lib.stages.noise")
    assert not any(m.startswith(("pipelines", "imulab")) for s in STAGES for m in module_closure(s.compute.__module__))


def test_new_module_changes_no_version_and_an_edit_changes_only_its_stages(tmp_path):
    root = _copy_sources(tmp_path)
    before = _digests(root)
    assert before == {s.name: source_digest(s.compute.__module__) for s in STAGES}  # the copy digests like the repo
    (root / "assets_lib" / "sim" / "new_effect.py").write_text("")
    (root / "assets_lib" / "newpkg").mkdir()
    (root / "assets_lib" / "newpkg" / "__init__.py").write_text('"""A new package nobody imports yet."""\n')
    assert _digests(root) == before

    with open(root / "assets_lib" / "calibration" / "rate_fit.py", "a") as f:
        f.write("# an edit\n")
    after = _digests(root)
    changed = {n for n in before if before[n] != after[n]}
    runs_it = {s.name for s in STAGES if "assets_lib.calibration.rate_fit" in module_closure(s.compute.__module__)}
    assert changed == runs_it and "gyro_rate_fit" in changed and "allan_deviation" not in changed
    assert "ingested_run" not in changed and "fleet_drift" not in changed


BACKGROUND_JOBS = ("full_run_on_code_copy",)  # in a second process from the start of the session (tests/conftest.py)


def _cli(work: Path, *args) -> tuple[int, str]:
    """An imulab command run on the code copy under ``work``, with its archive and data dir."""
    env = {**os.environ, "PYTHONPATH": str(work / "code"), "PYTHONWARNINGS": "ignore"}
    res = subprocess.run([sys.executable, "-m", "imulab.cli", *args, "--archive", str(work / "landing"),
                          "--data-dir", str(work / "data")], env=env, cwd=work, capture_output=True, text=True,
                         timeout=600, check=False)
    return res.returncode, res.stdout + res.stderr


def full_run_on_code_copy(work: Path) -> None:
    """A copy of the code, a realistic archive and ``imulab run --certificates`` on it (every stage materialized: a
    plain run leaves the certificates for ``imulab certificates``, and reprocess, which covers every stage, would
    render them); the run's exit status and output in ``work / "run.json"``."""
    from prod_helpers import write_realistic_archive

    _copy_sources(work / "code", ("assets_lib", "raw_schemas", "pipelines", "imulab"))
    write_realistic_archive(work / "landing")
    rc, out = _cli(work, "run", "--certificates")
    (work / "run.json").write_text(json.dumps({"rc": rc, "out": out}))


@pytest.mark.slow
def test_empty_module_leaves_reprocess_with_nothing_to_do(background_job):
    """The real commands on a copy of the code: ``imulab run --certificates`` (this module's background job,
    ``full_run_on_code_copy``), add an empty module, ``imulab reprocess --dry-run``."""
    work = background_job("full_run_on_code_copy")
    code = work / "code"
    run = json.loads((work / "run.json").read_text())
    assert run["rc"] == 0, run["out"]
    (code / "assets_lib" / "sim" / "new_effect.py").write_text("")
    rc, out = _cli(work, "reprocess", "--dry-run")
    assert rc == 0 and "nothing to reprocess" in out and " 0 stale" in out, out
    with open(code / "assets_lib" / "calibration" / "rate_fit.py", "a") as f:  # the check can fail
        f.write("# an edit\n")
    rc, out = _cli(work, "reprocess", "--dry-run")
    # the stages of the module that imports rate_fit (assets_lib/stages/calibration.py) and their downstreams
    assert rc == 0 and "gyro_rate_fit: 1 stale" in out and "plateaus: 2 stale" in out, out
    assert "ingested_run:" not in out, out
    # only the source digest moved: every stale stage keeps its declared version (X+src.a -> X+src.b)
    bumps = re.findall(r"code version (\w+)\+src\.\w+ -> (\w+)\+src", out)
    assert bumps and all(a == b for a, b in bumps), out


def test_import_scan_walks_statements_like_ast_walk():
    """The source digests' import scan visits statements only (``sources._statements``); it must find exactly the
    imports a full ``ast.walk`` finds, in every project module (function bodies, try/except, if, with, match)."""
    import ast

    from assets_lib.stages.sources import PROJECT_PACKAGES, ROOT, _statements

    sample = "import a\ntry:\n    import b\nexcept ImportError:\n    from c import d\nelse:\n    import e\nfinally:\n" \
             "    import f\ndef g():\n    if x:\n        import h\n    with y:\n        from . import i\n" \
             "class K:\n    def m(self):\n        for _ in z:\n            import j\n        while w:\n            pass\n" \
             "        else:\n            import k\nmatch v:\n    case 1:\n        import l\n"
    trees = [ast.parse(sample)] + [ast.parse(f.read_text()) for pkg in PROJECT_PACKAGES
                                   for f in sorted((ROOT / pkg).rglob("*.py"))]
    for tree in trees:
        full = [ast.dump(n) for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
        fast = [ast.dump(n) for n in _statements(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
        assert sorted(fast) == sorted(full)
    assert len([n for n in _statements(trees[0]) if isinstance(n, (ast.Import, ast.ImportFrom))]) == 10

