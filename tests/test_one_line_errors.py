"""Every error about the user's input is one line on stderr, whether the config check finds it
before the job starts or the job finds it while it runs (a weights path, a file's content):
no Hydra job line, no HYDRA_FULL_ERROR hint, no traceback (fusion_depth.config.hydra_main).
A bug keeps its traceback."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from helpers import run_module, save_untrained_checkpoint

# What a run may print to stderr before its error: the seed, and Lightning's notices.
_NOTICES = ("Seed set to", "Using ", "GPU available", "TPU available", "`Trainer(")

_DATASET = {"name": "procedural", "min_depth": 0.5, "max_depth": 80.0, "depth_scale": 10.0}


def _error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.strip().splitlines() if not line.startswith(_NOTICES)]


def _missing_prior_weights(tmp: Path) -> tuple[list[str], str]:
    missing = tmp / "no-such-prior"
    args = ["prior=depth_anything_v2", f"prior.weights={missing}"]
    return ["fusion_depth.train", "experiment=smoke", *args], str(missing)


def _prior_state_dict_a_list(tmp: Path) -> tuple[list[str], str]:
    prior = tmp / "prior.ckpt"
    torch.save({"state_dict": [torch.zeros(2)], "fusion_depth_config": {}}, prior)
    args = ["prior=checkpoint", f"prior.weights={prior}"]
    return ["fusion_depth.train", "experiment=smoke", *args], str(prior)


def _corrupt_checkpoint(tmp: Path) -> tuple[list[str], str]:
    ckpt = save_untrained_checkpoint(tmp / "model.ckpt", "rgb", _DATASET, backbone="resnet18")
    ckpt.write_bytes(ckpt.read_bytes()[:4000])  # cut short, as by a full disk or a copy
    return ["fusion_depth.evaluate", f"ckpt_path={ckpt}"], str(ckpt)


def _garbage_checkpoint(tmp: Path) -> tuple[list[str], str]:
    ckpt = tmp / "notes.ckpt"
    ckpt.write_text("not a checkpoint\n")
    return ["fusion_depth.predict", f"ckpt_path={ckpt}", f"input={tmp}"], str(ckpt)


def _bad_value_found_by_the_job(tmp: Path) -> tuple[list[str], str]:
    return ["fusion_depth.train", "experiment=smoke", "optimizer.lr=-1"], "optimizer.lr=-1"


@pytest.mark.slow
@pytest.mark.parametrize(
    "make",
    [
        _missing_prior_weights,
        _prior_state_dict_a_list,
        _corrupt_checkpoint,
        _garbage_checkpoint,
        _bad_value_found_by_the_job,
    ],
)
def test_a_job_time_error_is_one_line_naming_what_is_wrong(tmp_path, make) -> None:
    args, named = make(tmp_path)
    env = {**os.environ, "FUSION_DEPTH_CACHE": str(tmp_path / "cache")}
    run = [*args, "logger=none"] if args[0] == "fusion_depth.train" else args
    done = run_module([*run, f"hydra.run.dir={tmp_path / 'run'}"], tmp_path, env=env)
    assert done.returncode == 1, done.stderr
    lines = _error_lines(done.stderr)
    assert len(lines) == 1 and named in lines[0], done.stderr
    assert "Traceback" not in done.stderr and "HYDRA_FULL_ERROR" not in done.stderr
    assert not done.stdout.strip() or "Error executing job" not in done.stdout


def test_a_bug_keeps_its_traceback_and_the_hint(capsys) -> None:
    """An error that is not about the user's input is reported as Hydra would: its traceback
    and the hint; a user error is its message alone."""
    from fusion_depth.config.hydra_main import _report
    from fusion_depth.errors import CommandError

    try:
        {}["missing"]
    except KeyError as err:
        _report(err)
    bug = capsys.readouterr().err
    assert "Traceback" in bug and "HYDRA_FULL_ERROR=1" in bug
    _report(CommandError("ckpt_path=x.ckpt: no such file"))
    assert capsys.readouterr().err == "ckpt_path=x.ckpt: no such file" + os.linesep
