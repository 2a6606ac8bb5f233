"""``python -m fusion_depth.evaluate``, checkpoint loading and flip test-time augmentation.

Checkpoints are untrained DepthNets saved the way training saves them, so no test trains.
"""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from helpers import REPO, compose_config
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate

from fusion_depth.evaluate.scoring import evaluate
from fusion_depth.metrics.depth import METRIC_KEYS, DepthMetrics
from fusion_depth.models.inference import predict_depth
from fusion_depth.runner.checkpoints import load_model
from fusion_depth.utils.checkpoint_file import CheckpointError


def _evaluate(overrides: list[str], run_dir: Path) -> list[dict]:
    cfg = compose_config(overrides, run_dir, config_name="evaluate")
    try:
        return evaluate(cfg)
    finally:
        GlobalHydra.instance().clear()


# --- flip test-time augmentation -----------------------------------------------------------


class _ToyNet(torch.nn.Module):
    """Stands in for DepthNet: depth from a convolution of the image, at half resolution
    (2x2 average pooling, which commutes with a mirror image of an even-width input)."""

    def __init__(self, kernel: torch.Tensor) -> None:
        super().__init__()
        self.fusion = SimpleNamespace(uses_sparse=False)
        self.register_buffer("kernel", kernel.view(1, 3, *kernel.shape[-2:]))

    def predict_depth(self, image: torch.Tensor, sparse: torch.Tensor | None = None):
        pad = self.kernel.shape[-1] // 2
        features = torch.nn.functional.conv2d(image, self.kernel, padding=pad)
        return 1.0 + torch.nn.functional.avg_pool2d(features, 2)


def test_flip_tta_of_a_mirror_symmetric_model_is_a_no_op() -> None:
    kernel = torch.rand(3, 3, 3)
    symmetric = _ToyNet(kernel + kernel.flip(-1))  # a left-right symmetric kernel
    image = torch.rand(2, 3, 32, 64)
    plain = predict_depth(symmetric, image, upsample="nearest")
    tta = predict_depth(symmetric, image, flip_tta=True, upsample="nearest")
    torch.testing.assert_close(tta, plain, rtol=1e-6, atol=1e-6)


def test_flip_tta_averages_with_the_mirrored_prediction_of_the_mirrored_image() -> None:
    net = _ToyNet(torch.arange(27.0).view(3, 3, 3) / 27)  # not symmetric
    image = torch.rand(1, 3, 32, 64)
    plain = predict_depth(net, image, size=(16, 32))
    mirrored = predict_depth(net, image.flip(-1), size=(16, 32)).flip(-1)
    tta = predict_depth(net, image, flip_tta=True, size=(16, 32))
    torch.testing.assert_close(tta, (plain + mirrored) / 2)
    assert not torch.allclose(plain, mirrored)


# --- checkpoints ---------------------------------------------------------------------------


def test_a_checkpoint_of_another_fusion_or_backbone_is_refused_by_name(checkpoints) -> None:
    with pytest.raises(CheckpointError, match="trained with fusion=concat, but fusion=rgb"):
        load_model(checkpoints["concat"], fusion="rgb")
    with pytest.raises(CheckpointError, match="trained with backbone=densenet169, but backbone"):
        load_model(checkpoints["concat"], backbone="resnet50")


def test_weights_that_do_not_fit_the_recorded_config_are_refused(checkpoints, tmp_path) -> None:
    checkpoint = torch.load(checkpoints["concat"], weights_only=True)
    checkpoint["fusion_depth_config"]["fusion"]["mode"] = "rgb"
    checkpoint["fusion_depth_config"]["model"]["net"]["fusion"] = "rgb"
    torch.save(checkpoint, tmp_path / "mixed.ckpt")
    with pytest.raises(CheckpointError, match=r"do not fit backbone=densenet169 fusion=rgb.*mix"):
        load_model(tmp_path / "mixed.ckpt")


def test_loading_never_runs_code_from_the_file(checkpoints, tmp_path) -> None:
    checkpoint = torch.load(checkpoints["rgb"], weights_only=True)
    checkpoint["payload"] = SimpleNamespace(note="an arbitrary object")  # needs full unpickling
    torch.save(checkpoint, tmp_path / "pickled.ckpt")
    with pytest.raises(CheckpointError, match="refused to load"):
        load_model(tmp_path / "pickled.ckpt")
    (tmp_path / "broken.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="broken.ckpt: not a readable"):
        load_model(tmp_path / "broken.ckpt")
    with pytest.raises(FileNotFoundError, match="missing.ckpt: no such file"):
        load_model(tmp_path / "missing.ckpt")


def test_a_foreign_dataset_reader_in_a_checkpoint_is_not_called(checkpoints, tmp_path) -> None:
    checkpoint = torch.load(checkpoints["rgb"], weights_only=True)
    checkpoint["fusion_depth_config"]["dataset"]["reader"]["_target_"] = "os.system"
    torch.save(checkpoint, tmp_path / "foreign.ckpt")
    with pytest.raises(CheckpointError, match=r"instantiation key .*dataset\.reader\._target_"):
        _evaluate([f"ckpt_path={tmp_path / 'foreign.ckpt'}"], tmp_path / "run")


# --- evaluate ------------------------------------------------------------------------------


@pytest.mark.slow
def test_evaluate_scores_the_checkpoints_dataset_and_writes_the_record(
    checkpoints, smoke_dataset, tmp_path
) -> None:
    (results,) = _evaluate([f"ckpt_path={checkpoints['concat']}"], tmp_path / "run")
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["test"] == results["test"]
    assert saved["split"] == "test" and saved["run"]["fusion"] == "concat"
    assert saved["run"]["dataset"] == saved["run"]["trained_on"] == "procedural"
    assert saved["test"]["num_images"] == smoke_dataset["reader"]["num_test"]
    assert saved["latency"]["mean_s"] > 0 and saved["latency"]["input_size"] == [64, 96]

    # The same numbers computed independently: predictions of the loaded net, scored directly.
    loaded = load_model(checkpoints["concat"])
    reader = instantiate(smoke_dataset["reader"])(split="test")
    metric = DepthMetrics(
        min_depth=smoke_dataset["min_depth"],
        max_depth=smoke_dataset["max_depth"],
        conditions=smoke_dataset["conditions"],
        distance_bins=list(range(0, 81, 10)),
    )
    for i in range(len(reader)):
        sample = reader[i]
        pred = predict_depth(loaded.net, sample["image"][None], sample["sparse"][None])
        metric.update(pred, sample["depth"][None], [sample["condition"]], torch.tensor([i]))
    expected = metric.results()
    for key in METRIC_KEYS:
        assert saved["test"][key] == pytest.approx(expected["overall"][key], rel=1e-6), key
    assert saved["test_by_condition"].keys() == expected["by_condition"].keys()
    assert saved["test_by_distance"].keys() == expected["by_distance"].keys()
    counts = [g["num_images"] for g in saved["test_by_condition"].values()]
    assert sum(counts) == saved["test"]["num_images"]

    rows = list(csv.DictReader((tmp_path / "run" / "per_image.csv").open()))
    assert len(rows) == saved["test"]["num_images"]
    assert [r["condition"] for r in rows] == [reader[i]["condition"] for i in range(len(reader))]

    # Deterministic: the same checkpoint and settings give the same numbers.
    (again,) = _evaluate([f"ckpt_path={checkpoints['concat']}"], tmp_path / "again")
    assert again["test"] == results["test"]


@pytest.mark.slow
def test_protocol_options_reach_the_numbers(checkpoints, tmp_path) -> None:
    base = [f"ckpt_path={checkpoints['rgb']}", "eval.bin_width=null"]
    (plain,) = _evaluate(base, tmp_path / "plain")
    (caps,) = _evaluate([*base, "eval.max_depth=[50,70,80]"], tmp_path / "caps")
    (pooled,) = _evaluate([*base, "eval.averaging=pooled"], tmp_path / "pooled")
    (cropped,) = _evaluate([*base, "eval.crop=garg", "split=val"], tmp_path / "crop")
    assert plain["test_by_distance"] == {} and list(plain["test_by_cap"]) == ["80"]
    assert list(caps["test_by_cap"]) == ["50", "70", "80"]
    assert caps["test"] == plain["test"]  # the headline is the largest cap
    assert caps["test_by_cap"]["50"]["num_pixels"] < plain["test"]["num_pixels"]
    assert pooled["test"]["num_pixels"] == plain["test"]["num_pixels"]
    assert pooled["test"]["rmse"] != pytest.approx(plain["test"]["rmse"])
    assert cropped["split"] == "val" and cropped["protocol"]["crop"] == "garg"
    # The built-in dataset keeps no full-resolution points: eval=radarnet scores its frames, and
    # the record says so (resolution network, as the records written before the key).
    (radarnet,) = _evaluate([*base, "eval=radarnet"], tmp_path / "radarnet")
    assert radarnet["protocol"]["resolution"] == "network"
    with pytest.raises(ValueError, match="eval.averaging='mean'"):
        _evaluate([*base, "eval.averaging=mean"], tmp_path / "bad")


def test_a_fusion_guard_that_does_not_match_fails_before_any_work(checkpoints, tmp_path) -> None:
    with pytest.raises(CheckpointError, match="trained with fusion=rgb, but fusion=add"):
        _evaluate([f"ckpt_path={checkpoints['rgb']}", "fusion=add"], tmp_path / "run")
    assert not (tmp_path / "run" / "metrics.json").exists()


@pytest.mark.slow
def test_a_folder_of_runs_is_rescored_run_by_run(checkpoints, tmp_path) -> None:
    sweep = tmp_path / "sweep"
    for name, fusion in (("fusion=rgb", "rgb"), ("fusion=concat", "concat")):
        (sweep / name).mkdir(parents=True)
        record = {"run": {}, "test": {}, "best_checkpoint": str(checkpoints[fusion])}
        (sweep / name / "metrics.json").write_text(json.dumps(record))
    # A run folder moved here from elsewhere: its record names the checkpoint where it was.
    moved = sweep / "moved"
    (moved / "checkpoints").mkdir(parents=True)
    shutil.copy(checkpoints["rgb"], moved / "checkpoints" / "epoch000-rmse1.0.ckpt")
    record = {"run": {}, "test": {}, "best_checkpoint": "/gone/checkpoints/epoch000-rmse1.0.ckpt"}
    (moved / "metrics.json").write_text(json.dumps(record))
    results = _evaluate([f"ckpt_path={sweep}", "eval.flip_tta=true"], tmp_path / "out")
    assert sorted(r["run"]["fusion"] for r in results) == ["concat", "rgb", "rgb"]
    assert (tmp_path / "out" / "moved" / "metrics.json").is_file()
    for name in ("fusion=rgb", "fusion=concat"):
        saved = json.loads((tmp_path / "out" / name / "metrics.json").read_text())
        assert saved["protocol"]["flip_tta"] is True
        assert (tmp_path / "out" / name / "per_image.csv").is_file()


@pytest.mark.slow
def test_the_command_line_entry_point(checkpoints, tmp_path) -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "fusion_depth.evaluate",
            f"ckpt_path={checkpoints['rgb']}",
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "| Condition" in result.stdout and "| Distance (m, cap 80)" in result.stdout
    assert "Inference latency per frame (64x96" in result.stdout
    assert "Tip" not in result.stdout + result.stderr
    assert (tmp_path / "run" / "metrics.json").is_file()


def test_dataset_settings_without_a_dataset_choice_are_refused(checkpoints, tmp_path) -> None:
    # experiment=smoke sets dataset sizes; without dataset=<name> they would silently not apply.
    with pytest.raises(ValueError, match=r"no dataset was chosen: add dataset=<name>"):
        _evaluate([f"ckpt_path={checkpoints['rgb']}", "experiment=smoke"], tmp_path / "run")
