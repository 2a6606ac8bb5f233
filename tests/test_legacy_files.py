"""Files written by an earlier release still work: a checkpoint and an exported ONNX model
written by fusion-depth 0.1.0 (before the package was rearranged into layers) evaluate to the
numbers that release printed, and predict alike; a run folder it left interrupted resumes.

``tests/fixtures/v0.1.0/`` (see its README) holds the files and ``expected_metrics.json``, the
``test`` and ``test_by_condition`` blocks of the ``metrics.json`` that release wrote for each.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import REPO, run_module

FIXTURES = REPO / "tests" / "fixtures" / "v0.1.0"
CHECKPOINT = FIXTURES / "concat_test_resnet.ckpt"
MODEL_FILE = FIXTURES / "concat_test_resnet.onnx"
EXPECTED = json.loads((FIXTURES / "expected_metrics.json").read_text())


def _close(a: float, b: float) -> bool:
    # fp32 convolutions round differently on other CPUs (oneDNN picks the kernel): a relative
    # 1e-5 on errors, and for the δ shares a handful of the 25,232 pixels.
    return math.isclose(a, b, rel_tol=1e-5, abs_tol=2e-4)


def _assert_same_numbers(got: dict, expected: dict, where: str) -> None:
    assert got.keys() >= expected.keys(), where
    for key, value in expected.items():
        if isinstance(value, dict):
            _assert_same_numbers(got[key], value, f"{where}.{key}")
        else:
            assert _close(got[key], value), f"{where}.{key}: {got[key]} != {value}"


@pytest.mark.slow
@pytest.mark.parametrize(
    ("key", "path"), [("ckpt_path", CHECKPOINT), ("model_file", MODEL_FILE)], ids=["ckpt", "onnx"]
)
def test_a_file_of_the_earlier_release_evaluates_to_its_numbers(
    key: str, path: Path, tmp_path: Path
) -> None:
    # A copy: the files are read where a user keeps them, never written.
    for file in FIXTURES.glob(f"{path.stem}*"):
        shutil.copy(file, tmp_path / file.name)
    run_dir = tmp_path / "scored"
    result = run_module(
        ["fusion_depth.evaluate", f"{key}={tmp_path / path.name}", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    record = json.loads((run_dir / "metrics.json").read_text())
    for block in ("test", "test_by_condition"):
        _assert_same_numbers(record[block], EXPECTED[key][block], block)


@pytest.mark.slow
def test_the_earlier_releases_files_predict_the_same_depth(tmp_path: Path) -> None:
    depths = {}
    # The checkpoint in fp32, as the file was exported (auto would pick bf16 on some CPUs).
    for key, path, extra in (
        ("ckpt_path", CHECKPOINT, ["precision=32-true"]),
        ("model_file", MODEL_FILE, []),
    ):
        out = tmp_path / key
        result = run_module(
            [
                "fusion_depth.predict",
                f"{key}={path}",
                "input=split:test",
                "npy=true",
                f"output_dir={out}",
                f"hydra.run.dir={tmp_path / 'hydra' / key}",
                *extra,
            ],
            cwd=tmp_path,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        files = sorted(out.rglob("*.npy"))
        assert len(files) == EXPECTED[key]["test"]["num_images"]
        depths[key] = np.stack([np.load(f) for f in files])
    # The checkpoint in PyTorch and its ONNX export in onnxruntime: the export's own tolerance.
    assert np.all(np.isfinite(depths["ckpt_path"]))
    np.testing.assert_allclose(depths["model_file"], depths["ckpt_path"], rtol=1e-3, atol=1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("bf16_cpu", [False, True], ids=["fp32-cpu", "bf16-cpu"])
def test_an_interrupted_run_folder_of_the_earlier_release_resumes_elsewhere(
    tmp_path: Path, bf16_cpu: bool
) -> None:
    """A run folder that release wrote (interrupted before its test stage, so ``last.ckpt`` but
    no ``metrics.json``), moved to another place, resumes under the same command and finishes
    with the numbers that release's own run printed, testing the best checkpoint it kept. That
    release named run folders with ``=`` and ``,``: the same command, without a run folder on
    its command line, finds the folder of that name. It ran in fp32 (``precision=auto`` on a
    CPU without bf16); on a CPU with bf16, ``auto`` goes on in fp32 as the run began."""
    hydra_record = yaml.safe_load(
        (FIXTURES / "interrupted_run" / ".hydra" / "hydra.yaml").read_text()
    )
    legacy_name = hydra_record["hydra"]["job"]["override_dirname"]
    assert "=" in legacy_name and "," in legacy_name
    run_dir = tmp_path / "outputs" / legacy_name
    shutil.copytree(FIXTURES / "interrupted_run", run_dir)
    overrides = yaml.safe_load((run_dir / ".hydra" / "overrides.yaml").read_text())
    script = (
        "import sys\n"
        "from fusion_depth.runner import speed\n"
        f"speed.supports_bf16 = lambda device: {bf16_cpu}  # as this CPU would answer\n"
        f"sys.argv = ['fusion_depth.train', *{overrides!r}]\n"
        "from fusion_depth.train.cli import main\n"
        "main()\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=1800
    )
    assert result.returncode == 0, result.stderr[-3000:]
    log = (run_dir / "train.log").read_text()
    assert f"resuming from {run_dir / 'checkpoints' / 'last.ckpt'}" in log
    record = json.loads((run_dir / "metrics.json").read_text())
    assert Path(record["best_checkpoint"]).parent == run_dir / "checkpoints"
    for block in ("test", "test_by_condition"):
        _assert_same_numbers(record[block], EXPECTED["interrupted_run"][block], block)
    resolved = yaml.safe_load((run_dir / "config_resolved.yaml").read_text())
    assert resolved["trainer"]["precision"] == "32-true"
    assert sorted(p.name for p in (tmp_path / "outputs").iterdir()) == [legacy_name]
