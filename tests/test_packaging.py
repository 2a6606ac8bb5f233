"""The package as users install it: a wheel (not an editable checkout) that carries ``conf/`` and
``sweeps/``, console commands, and a smoke sweep run from a folder outside the checkout, whose
printed best checkpoint is pasted back, unquoted, into ``evaluate``."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from helpers import REPO

from fusion_depth.version import __version__

COMMANDS = ("train", "evaluate", "predict", "export", "prepare", "report", "bench", "score_sparse")


def _run(args: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A wheel built, as ``pip wheel .`` does, from a copy of the checkout's sources (building
    in place would leave build folders in the checkout)."""
    source = tmp_path_factory.mktemp("source")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, source / name)
    for name in ("conf", "sweeps", "fusion_depth"):
        shutil.copytree(REPO / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
    dist = tmp_path_factory.mktemp("dist")
    done = _run(
        [sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "-w", str(dist), "-q"],
        cwd=source,
        env=dict(os.environ),
    )
    assert done.returncode == 0, done.stderr
    (found,) = dist.glob("fusion_depth-*.whl")
    return found


@pytest.mark.slow
def test_the_wheel_carries_every_config_sweep_and_module(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    expected = {
        f"fusion_depth/{p.relative_to(REPO).as_posix()}"
        for folder in ("conf", "sweeps")
        for p in (REPO / folder).rglob("*.yaml")
    }
    expected |= {p.relative_to(REPO).as_posix() for p in (REPO / "fusion_depth").rglob("*.py")}
    assert expected - names == set()
    # One version: the wheel's is fusion_depth.__version__ (pyproject.toml reads version.py).
    assert wheel.name.startswith(f"fusion_depth-{__version__}-")
    (metadata,) = [n for n in names if n.endswith(".dist-info/METADATA")]
    assert f"\nVersion: {__version__}\n" in zipfile.ZipFile(wheel).read(metadata).decode()
    (entry_points,) = [n for n in names if n.endswith("entry_points.txt")]
    text = zipfile.ZipFile(wheel).read(entry_points).decode()
    for command in COMMANDS:
        script = f"fusion-depth-{command.replace('_', '-')}"
        assert f"{script} = fusion_depth.{command}:main" in text


@pytest.mark.slow
def test_the_installed_package_runs_a_smoke_sweep_from_any_folder(wheel, tmp_path) -> None:
    target = tmp_path / "site"
    done = _run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--target", str(target), str(wheel)],
        cwd=tmp_path,
        env=dict(os.environ),
    )
    assert done.returncode == 0, done.stderr
    # The installed copy comes first on the path: it, not the checkout, is what runs.
    env = {**os.environ, "PYTHONPATH": str(target)}
    work = tmp_path / "elsewhere"
    work.mkdir()
    where = _run(
        [sys.executable, "-c", "import fusion_depth.config as c; print(c.CONF_DIR, c.SWEEPS_DIR)"],
        work,
        env,
    )
    conf, sweeps = where.stdout.split()
    assert Path(conf) == target / "fusion_depth" / "conf"
    assert Path(sweeps) == target / "fusion_depth" / "sweeps"

    # A packaged sweep by name, through the console command, 2 jobs of 1 epoch.
    sweep = _run(
        [
            str(target / "bin" / "fusion-depth-train"),
            "--config-name",
            "procedural_weather",
            "-m",
            "experiment=smoke",
            "logger=none",
            "seed=42",
            "fusion=rgb,concat",
            "trainer.max_epochs=1",
        ],
        work,
        env,
    )
    assert sweep.returncode == 0, sweep.stderr[-3000:]
    runs = sorted((work / "multirun" / "procedural_weather").rglob("metrics.json"))
    assert [r.parent.name for r in runs] == [
        "experiment-smoke+fusion-concat+seed-42+trainer.max_epochs-1",
        "experiment-smoke+fusion-rgb+seed-42+trainer.max_epochs-1",
    ]
    best = json.loads(runs[0].read_text())["best_checkpoint"]
    assert best in sweep.stdout + sweep.stderr  # printed ...

    # ... and pasted back unquoted, relative to the folder.
    pasted = os.path.relpath(best, work)
    scored = _run([str(target / "bin" / "fusion-depth-evaluate"), f"ckpt_path={pasted}"], work, env)
    assert scored.returncode == 0, scored.stderr[-3000:]
    written = re.search(r"Written to (\S+metrics\.json)", scored.stdout)
    assert written and Path(written[1]).is_file()
    assert json.loads(Path(written[1]).read_text())["checkpoint"] == str(Path(best).resolve())
