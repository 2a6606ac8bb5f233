"""Exported model files run by their engines (``fusion_depth.export.runtime``):
``evaluate model_file=`` scores them by the checkpoint's protocol, ``predict model_file=`` writes
their depth, ``report --compare engine=torch`` pairs them with their checkpoint, and sidecars
that are missing or wrong are refused in one line naming the file and the key.

The checkpoint is an untrained ResNet-18 DepthNet (``conftest``, ``spread=True``) at the smoke
size 64×96; each format is exported once per module.
"""

from __future__ import annotations

import csv
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import compose_config, save_untrained_checkpoint
from hydra.core.global_hydra import GlobalHydra
from PIL import Image

from fusion_depth.data.depth_io import read_depth_png, write_depth_png
from fusion_depth.errors import ConfigError
from fusion_depth.evaluate.scoring import evaluate
from fusion_depth.export import (
    ExportedModel,
    ModelFileError,
    SidecarError,
    export_model,
    load_exported,
    sidecar_path,
)
from fusion_depth.metrics.depth import METRIC_KEYS
from fusion_depth.models.inference import predict_depth
from fusion_depth.predict.cli import predict
from fusion_depth.report import compare_to_baseline, group_runs
from fusion_depth.report import main as report_main
from fusion_depth.runner.checkpoints import dataset_config, load_model, make_reader
from fusion_depth.runner.record import load_runs
from fusion_depth.utils.checkpoint_file import CheckpointError

H, W = 64, 96
RTOL = 1e-3  # fp32 files: the verification tolerance


def _run(config: str, overrides: list[str], run_dir: Path):
    cfg = compose_config(overrides, run_dir, config_name=config)
    try:
        return evaluate(cfg) if config == "evaluate" else predict(cfg)
    finally:
        GlobalHydra.instance().clear()


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory, smoke_dataset: dict) -> Path:
    root = tmp_path_factory.mktemp("ckpt18")
    return save_untrained_checkpoint(
        root / "concat.ckpt", "concat", smoke_dataset, backbone="resnet18", spread=True
    )


@pytest.fixture(scope="module")
def model_files(checkpoint: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The checkpoint as ONNX (dynamic batch) and as an OpenVINO fp32 IR with its batch fixed
    to 2 (so evaluation's batches of 4 and 1 run in chunks of 2, the last one filled up)."""
    root = tmp_path_factory.mktemp("exported")
    loaded = load_model(checkpoint)
    return {
        "onnx": export_model(loaded, "onnx", root / "m.onnx"),
        "openvino": export_model(
            loaded, "openvino", root / "m.xml", precision="fp32", batch_size=2
        ),
    }


@pytest.fixture(scope="module")
def scored(checkpoint: Path, model_files: dict[str, Path], tmp_path_factory) -> Path:
    """The checkpoint and both files evaluated on the test split, into one folder."""
    root = tmp_path_factory.mktemp("scored")
    _run("evaluate", [f"ckpt_path={checkpoint}"], root / "torch")
    for fmt, path in model_files.items():
        _run("evaluate", [f"model_file={path}"], root / fmt)
    return root


@pytest.mark.slow
@pytest.mark.parametrize("fmt,engine", [("onnx", "onnxruntime"), ("openvino", "openvino-fp32")])
def test_evaluate_model_file_gives_the_checkpoints_metrics(
    fmt: str, engine: str, scored: Path, checkpoint: Path, model_files: dict[str, Path]
) -> None:
    torch_run = json.loads((scored / "torch" / "metrics.json").read_text())
    run = json.loads((scored / fmt / "metrics.json").read_text())
    assert run["run"]["engine"] == engine and torch_run["run"]["engine"] == "torch"
    assert run["model_file"] == str(model_files[fmt].resolve())
    assert run["checkpoint"] == torch_run["checkpoint"] == str(checkpoint.resolve())
    assert run["split"] == "test" and run["protocol"] == torch_run["protocol"]
    assert run["test"]["num_images"] == torch_run["test"]["num_images"] == 5
    assert run["test"]["num_pixels"] == torch_run["test"]["num_pixels"]
    for key in METRIC_KEYS:
        assert run["test"][key] == pytest.approx(torch_run["test"][key], rel=RTOL, abs=1e-6), key
    # The identity report groups by: the training run's, on the dataset scored.
    for key in ("dataset", "sensor", "model", "backbone", "fusion", "loss", "seed", "overrides"):
        assert run["run"][key] == torch_run["run"][key], key
    rows = list(csv.DictReader((scored / fmt / "per_image.csv").open()))
    torch_rows = list(csv.DictReader((scored / "torch" / "per_image.csv").open()))
    assert [(r["index"], r["condition"]) for r in rows] == [
        (r["index"], r["condition"]) for r in torch_rows
    ]


@pytest.mark.slow
def test_report_pairs_each_exported_model_with_its_checkpoint(scored: Path, capsys) -> None:
    comparisons = compare_to_baseline(group_runs(load_runs(scored)), {"engine": "torch"})
    assert sorted(c.group["engine"] for c in comparisons) == ["onnxruntime", "openvino-fp32"]
    for c in comparisons:
        assert c.baseline["engine"] == "torch" and c.num_images == 5
        assert c.seeds == (0,)  # paired by the training run's seed
        assert abs(c.results["all"].mean) < 0.01  # fp32 files: the same depth to 1e-3
    assert report_main([str(scored), "--compare", "engine=torch"]) in (0, None)
    table = capsys.readouterr().out
    assert "| Engine" in table and "openvino-fp32" in table and "onnxruntime" in table


@pytest.mark.slow
def test_the_fixed_batch_file_runs_any_batch(checkpoint: Path, model_files) -> None:
    net = load_exported(model_files["openvino"]).net
    assert isinstance(net, ExportedModel) and net.info.batch_size == 2
    rng = np.random.default_rng(0)
    image = torch.from_numpy(rng.random((3, 3, H, W), dtype=np.float32))
    sparse = torch.zeros(3, 1, H, W)
    sparse[..., ::8, ::8] = 20.0
    depth = predict_depth(net, image, sparse)
    expected = predict_depth(load_model(checkpoint).net, image, sparse)
    torch.testing.assert_close(depth, expected, rtol=RTOL, atol=0)
    with pytest.raises(ValueError, match=r"model_file=.*m.xml takes 64×96 inputs .* got 32×96"):
        net(image[..., :32, :], sparse[..., :32, :])


@pytest.mark.slow
def test_predict_model_file_writes_the_depth_pngs(
    checkpoint: Path, model_files: dict[str, Path], tmp_path: Path
) -> None:
    out = tmp_path / "pred"
    summary = _run(
        "predict",
        [
            f"model_file={model_files['openvino']}",
            "input=split:test",
            "limit=3",
            f"output_dir={out}",
        ],
        tmp_path / "run",
    )
    assert summary.ok and len(summary.written) == 3
    loaded = load_model(checkpoint)
    reader = make_reader(dataset_config(loaded, None), loaded.path)(split="test")
    for index in range(3):
        sample = reader[index]
        expected = predict_depth(loaded.net, sample["image"][None], sample["sparse"][None])
        written = read_depth_png(out / f"test_{index:06d}.png")  # 1/256 m steps
        np.testing.assert_allclose(written, expected[0, 0].numpy(), rtol=RTOL, atol=1 / 256)
        assert (out / f"test_{index:06d}.viz.png").is_file()
    # An image of another size than the file's is skipped, naming the size the file takes.
    images, sparse = tmp_path / "images", tmp_path / "sparse"
    images.mkdir(), sparse.mkdir()
    Image.new("RGB", (W, H)).save(images / "fits.png")
    Image.new("RGB", (W, 32)).save(images / "small.png")
    write_depth_png(sparse / "fits.png", np.zeros((H, W), np.float32))
    write_depth_png(sparse / "small.png", np.zeros((32, W), np.float32))
    overrides = [f"model_file={model_files['onnx']}", f"input={images}", f"sparse={sparse}"]
    summary = _run("predict", [*overrides, f"output_dir={tmp_path / 'out2'}"], tmp_path / "r2")
    assert [p.name for p in summary.written] == ["fits.png"]
    (skipped,) = summary.skipped
    assert skipped.source.endswith("small.png") and "takes 64×96 inputs" in skipped.reason


@pytest.mark.slow
def test_a_model_is_named_by_ckpt_path_or_model_file_not_both(checkpoint, model_files, tmp_path):
    both = [f"ckpt_path={checkpoint}", f"model_file={model_files['onnx']}"]
    for config, extra in (("evaluate", []), ("predict", ["input=split:test"])):
        with pytest.raises(ConfigError, match=r"ckpt_path=.* and model_file=.*: give one"):
            _run(config, [*both, *extra], tmp_path / "run")
        with pytest.raises(ConfigError, match=r"ckpt_path=null and model_file=null: give"):
            _run(config, extra, tmp_path / "run")
    assert not (tmp_path / "run" / "metrics.json").exists()


def _copy(model_file: Path, folder: Path, edit) -> Path:
    """``model_file`` and its sidecar copied into ``folder``, the sidecar changed by ``edit``."""
    folder.mkdir(parents=True, exist_ok=True)
    copy = folder / model_file.name
    shutil.copy(model_file, copy)
    info = json.loads(sidecar_path(model_file).read_text())
    edit(info)
    sidecar_path(copy).write_text(json.dumps(info))
    return copy


@pytest.mark.parametrize(
    "edit,message",
    [
        (lambda i: i.pop("fusion"), r"no key 'fusion' \(expected one of"),
        (lambda i: i.update(min_depth="0.5"), r"key 'min_depth' is '0.5'; expected a number"),
        (lambda i: i.update(max_depth=True), r"key 'max_depth' is True; expected a number"),
        (lambda i: i.update(format="tflite"), r"key 'format' is 'tflite'; expected one of"),
        (lambda i: i.update(engine="coreml"), r"key 'engine' is 'coreml'; expected one of"),
        (lambda i: i.update(engine="openvino"), r"key 'engine' is 'openvino', which runs openvino"),
        (lambda i: i.update(engine="tensorrt"), r"key 'engine' is 'tensorrt', which runs tensorrt"),
        (lambda i: i.update(precision="fp8"), r"'precision' is 'fp8'; engine 'onnxruntime' runs"),
        (lambda i: i.update(precision="fp16"), r"'precision' is 'fp16'; engine 'onnxruntime' runs"),
        (lambda i: i["inputs"].pop(), r"key 'inputs' names \['image'\]; a fusion=concat model"),
        (lambda i: i["inputs"][0].update(shape=[1, 3, 70, 96]), r"'inputs\[0\].shape' has height"),
        (
            lambda i: i["dataset_config"]["reader"].update(_target_="os.system"),
            r"refused; it holds the instantiation key dataset_config.reader._target_",
        ),
    ],
)
def test_a_hostile_sidecar_is_refused_naming_file_and_key(
    edit, message: str, model_files: dict[str, Path], tmp_path: Path
) -> None:
    copy = _copy(model_files["onnx"], tmp_path, edit)
    with pytest.raises((SidecarError, CheckpointError)) as err:
        load_exported(copy)
    text = str(err.value)
    assert "\n" not in text and str(sidecar_path(copy)) in text
    assert re.search(message, text), text


def test_missing_or_unreadable_sidecars_and_a_sidecar_without_dataset(
    model_files: dict[str, Path], tmp_path: Path
) -> None:
    lone = tmp_path / "lone" / "m.onnx"
    lone.parent.mkdir()
    shutil.copy(model_files["onnx"], lone)
    with pytest.raises(SidecarError, match=r"model_file=.*m.onnx: no sidecar m.onnx.json next"):
        load_exported(lone)
    sidecar_path(lone).write_text("{not json")
    with pytest.raises(SidecarError, match=r"m.onnx.json: not valid JSON"):
        load_exported(lone)
    with pytest.raises(FileNotFoundError, match=r"model_file=.*nothing.xml: no such file"):
        load_exported(tmp_path / "nothing.xml")
    # Written before sidecars carried the dataset: evaluate needs dataset=.
    copy = _copy(model_files["onnx"], tmp_path / "old", lambda i: i.pop("dataset_config"))
    with pytest.raises(CheckpointError, match=r"model_file=.*: its sidecar records no dataset"):
        _run("evaluate", [f"model_file={copy}"], tmp_path / "run")
    assert not (tmp_path / "run" / "metrics.json").exists()


# --- damaged model files: one line naming the file, before any data is made ------------------


def _copy_ir(model_file: Path, folder: Path) -> Path:
    """An OpenVINO IR (``.xml``, ``.bin``) and its sidecar copied into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for path in (model_file, model_file.with_suffix(".bin"), sidecar_path(model_file)):
        shutil.copy(path, folder / path.name)
    return folder / model_file.name


def _refused_in_one_line(model_file: Path, error: type[Exception], tmp_path: Path) -> str:
    with pytest.raises(error) as err:
        _run("evaluate", [f"model_file={model_file}"], tmp_path / "run")
    text = str(err.value)
    assert "\n" not in text and str(model_file.parent) in text, text
    assert not (tmp_path / "run" / "metrics.json").exists()
    return text


def test_a_truncated_onnx_file_is_refused_naming_it(model_files, tmp_path: Path) -> None:
    copy = _copy(model_files["onnx"], tmp_path / "cut", lambda info: None)
    data = copy.read_bytes()
    copy.write_bytes(data[: len(data) // 2])
    text = _refused_in_one_line(copy, ModelFileError, tmp_path)
    assert f"model_file={copy}: onnxruntime cannot load it (" in text and "export it again" in text


@pytest.mark.parametrize("damage", ["truncated", "missing"])
def test_a_damaged_openvino_weights_file_is_refused_naming_it(
    damage: str, model_files, tmp_path: Path
) -> None:
    copy = _copy_ir(model_files["openvino"], tmp_path / damage)
    weights = copy.with_suffix(".bin")
    if damage == "missing":
        weights.unlink()
    else:
        weights.write_bytes(weights.read_bytes()[:1000])
    text = _refused_in_one_line(copy, ModelFileError, tmp_path)
    assert f"model_file={copy}: openvino cannot load it (" in text


def test_a_sidecar_nested_beyond_reason_is_refused(model_files, tmp_path: Path) -> None:
    copy = _copy(model_files["onnx"], tmp_path / "deep", lambda info: None)
    sidecar_path(copy).write_text("[" * 100_000 + "]" * 100_000)
    text = _refused_in_one_line(copy, SidecarError, tmp_path)
    assert f"{sidecar_path(copy)}: nested too deeply to be a sidecar" == text


@pytest.mark.parametrize(
    "fmt,edit,message",
    [
        (
            "onnx",
            lambda i: [x.update(shape=["batch", x["shape"][1], 128, 96]) for x in i["inputs"]],
            r"input 'image' has shape \['batch', 3, 64, 96\] in the file, but its sidecar says "
            r"\['batch', 3, 128, 96\]",
        ),
        (
            "openvino",
            lambda i: [x.update(shape=["batch", *x["shape"][1:]]) for x in i["inputs"]],
            r"input 'image' has shape \[2, 3, 64, 96\] in the file, but its sidecar says "
            r"\['batch', 3, 64, 96\]",
        ),
    ],
)
def test_a_sidecar_whose_shapes_differ_from_the_file_is_refused_before_any_data(
    fmt: str, edit, message: str, model_files, tmp_path: Path
) -> None:
    """Refused when the file is opened: no test split is made at the sidecar's size, and the
    engine never sees an input of the wrong shape."""
    if fmt == "onnx":
        copy = _copy(model_files["onnx"], tmp_path / "shape", edit)
    else:
        copy = _copy_ir(model_files["openvino"], tmp_path / "shape")
        info = json.loads(sidecar_path(copy).read_text())
        edit(info)
        sidecar_path(copy).write_text(json.dumps(info))
    text = _refused_in_one_line(copy, ModelFileError, tmp_path)
    assert re.search(message, text), text
