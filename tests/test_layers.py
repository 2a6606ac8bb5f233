"""The package's layers hold (``[tool.importlinter]`` in ``pyproject.toml``, checked by
``lint-imports`` in CI): the contracts pass on the package as it is, the layers name every
top-level part, and a contract fails as soon as a lower layer imports a higher one (inside a
function too), or a science package imports Hydra, OmegaConf or Lightning (through a helper of
``utils`` too)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib
from helpers import REPO

CONTRACT = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"]
LINT_IMPORTS = str(Path(sys.executable).with_name("lint-imports"))


def _lint_imports_with(root: Path, module: str, code: str) -> subprocess.CompletedProcess:
    """``lint-imports`` on a copy of the package under ``root`` with ``code`` appended to
    ``module`` (a path inside the package)."""
    shutil.copytree(
        REPO / "fusion_depth", root / "fusion_depth", ignore=shutil.ignore_patterns("*.pyc")
    )
    shutil.copy(REPO / "pyproject.toml", root)
    path = root / "fusion_depth" / module
    path.write_text(path.read_text() + f"\n\n{code}\n")
    return _lint_imports(root)


def _lint_imports(cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [LINT_IMPORTS, "--no-cache"], cwd=cwd, capture_output=True, text=True, timeout=300
    )


def test_the_contract_names_every_part_of_the_package() -> None:
    (layers,) = [c for c in CONTRACT["contracts"] if c["id"] == "layers"]
    assert layers["type"] == "layers" and layers["exhaustive"] is True
    named = {
        part.strip() for layer in layers["layers"] for part in layer.replace(":", "|").split("|")
    }
    package = REPO / "fusion_depth"
    parts = {p.stem for p in package.iterdir() if p.suffix == ".py" and p.stem != "__init__"}
    parts |= {p.name for p in package.iterdir() if (p / "__init__.py").is_file()}
    assert named == parts


def test_the_package_keeps_its_layers() -> None:
    result = _lint_imports(REPO)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert f"{len(CONTRACT['contracts'])} kept, 0 broken" in result.stdout


@pytest.mark.parametrize(
    ("module", "upward", "in_function"),
    [
        ("models/base.py", "fusion_depth.runner.module", True),
        ("utils/atomic.py", "fusion_depth.data.depth_io", False),
        ("runner/resume.py", "fusion_depth.config.run_dirs", True),
        ("data/cache.py", "fusion_depth.prepare.cli", True),
        ("export/runtime.py", "fusion_depth.predict.files", True),
    ],
)
def test_an_upward_import_breaks_the_contract(
    tmp_path: Path, module: str, upward: str, in_function: bool
) -> None:
    statement = f"import {upward}"
    if in_function:
        statement = f"def _upward():\n    {statement}\n\n    return {upward}"
    result = _lint_imports_with(tmp_path, module, statement)
    assert result.returncode == 1, result.stdout[-3000:]
    lower = "fusion_depth." + module.removesuffix(".py").replace("/", ".")
    assert f"{lower} -> {upward}" in result.stdout


@pytest.mark.parametrize(
    ("module", "line", "broken"),
    [
        ("models/fusion.py", "import omegaconf", "fusion_depth.models.fusion -> omegaconf"),
        ("losses/depth_loss.py", "import lightning", "fusion_depth.losses.depth_loss -> lightning"),
        # A helper the science packages import brings Hydra with it.
        ("utils/overrides.py", "import hydra", "fusion_depth.utils.overrides -> hydra"),
        # The science packages in order: data is below the models.
        ("data/base.py", "import fusion_depth.models.fusion", "fusion_depth.data.base -> "),
    ],
)
def test_a_science_import_breaks_a_contract(
    tmp_path: Path, module: str, line: str, broken: str
) -> None:
    result = _lint_imports_with(tmp_path, module, f"{line}  # noqa")
    assert result.returncode == 1, result.stdout[-3000:]
    assert broken in result.stdout and "BROKEN" in result.stdout, result.stdout[-3000:]
