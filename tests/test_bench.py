"""The benchmark's output schema and its arithmetic on a tiny configuration (no timing asserts)."""

from __future__ import annotations

import json
import math
import mmap
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from fusion_depth.bench import cli as bench
from fusion_depth.bench import stages as benchmarks

TINY = ["--runs", "2", "--train-steps", "1", "--warmup", "0", "--data-batches", "2"]
REQUIRED = (
    "infer_latency_s_median",
    "infer_latency_s_p95",
    "train_samples_per_s",
    "data_samples_per_s_per_worker",
    "peak_memory_mb",
    "achieved_gflops",
    "peak_gflops",
)


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("FUSION_DEPTH_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _run(tmp_path: Path, *args: str) -> dict:
    out = tmp_path / "bench.json"
    assert bench.main([*args, "--json", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.mark.slow
def test_bench_writes_every_key_with_the_baseline(
    tmp_path: Path, cache: Path, capsys: pytest.CaptureFixture
) -> None:
    result = _run(tmp_path, "experiment=smoke", "fusion=concat", "--baseline", *TINY)
    for key in (*REQUIRED, "baseline_infer_latency_s_median", "baseline_train_samples_per_s"):
        assert isinstance(result[key], float) and result[key] > 0, key
    settings = result["settings"]
    assert settings["fusion"] == "concat" and settings["backbone"] == "resnet10t"
    assert (settings["height"], settings["width"], settings["batch_size"]) == (64, 96, 2)
    assert settings["precision"] in ("bf16-mixed", "32-true")
    assert result["machine"]["cpu_cores"] >= 1 and result["versions"]["torch"]
    # The derived figures are the measured ones combined, not separate guesses.
    assert result["infer_speedup"] == pytest.approx(
        result["baseline_infer_latency_s_median"] / result["infer_latency_s_median"]
    )
    assert result["train_speedup"] == pytest.approx(
        result["train_samples_per_s"] / result["baseline_train_samples_per_s"]
    )
    assert result["achieved_gflops"] == pytest.approx(
        result["infer_gflop_per_frame"] / result["infer_latency_s_median"]
    )
    assert result["train_samples_per_s"] == pytest.approx(2 / result["train"]["step_s_median"])
    # A training step (forward, backward) costs more than twice a batch-1 forward per sample.
    assert result["train_gflop_per_step"] > 2 * 2 * result["infer_gflop_per_frame"] * 0.9
    data = result["data"]
    assert data["workers"] == 1 and data["dataset"] == "procedural"
    assert data["loader_samples_per_s"] == result["data_samples_per_s_per_worker"]
    assert data["augment_samples_per_s"] > 0 and data["pipeline_samples_per_s"] > 0
    printed = capsys.readouterr().out
    assert "(baseline)" in printed and "speed-up" in printed and str(tmp_path) in printed


def test_bench_runs_only_the_stages_asked_for(tmp_path: Path, cache: Path) -> None:
    result = _run(
        tmp_path, "experiment=smoke", "trainer.precision=32-true", "--only", "infer", *TINY
    )
    assert result["infer_latency_s_median"] > 0 and result["settings"]["precision"] == "32-true"
    for key in ("train_samples_per_s", "data_samples_per_s_per_worker", "peak_gflops"):
        assert result[key] is None, key
    assert "baseline_infer_latency_s_median" not in result
    assert "train_gflop_per_step" not in result and result["infer_gflop_per_frame"] > 0
    assert not (cache / "procedural").exists()  # no data stage, so nothing was rendered


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["fusion=fancy"], "fusion"),
        (["--only", "infer,warp"], "warp"),
        (["--runs", "0"], "--runs=0"),
        (["--only", "prepare", "--cores", "0"], "--cores=0"),
        (["dataset.height=100"], "dataset.height=100"),
        (["trainer.precision=fp8"], "trainer.precision"),
    ],
)
def test_bench_refuses_bad_input_naming_it(
    args: list[str], named: str, capsys: pytest.CaptureFixture
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["experiment=smoke", *args])
    assert exit_info.value.code == 2
    assert named in capsys.readouterr().err


def test_count_flops_counts_multiply_adds_twice() -> None:
    layer = nn.Linear(8, 4, bias=False)
    assert benchmarks.count_flops(lambda: layer(torch.ones(3, 8))) == 2 * 3 * 8 * 4


def test_time_calls_times_only_the_runs_after_warmup() -> None:
    calls = []
    times = benchmarks.time_calls(lambda: calls.append(1), torch.device("cpu"), warmup=2, runs=5)
    assert len(calls) == 7 and len(times) == 5 and all(t >= 0 for t in times)


@pytest.mark.skipif(
    not Path("/proc/self/clear_refs").exists(), reason="per-stage peaks need Linux's clear_refs"
)
def test_peak_memory_sees_a_large_allocation() -> None:
    memory = benchmarks.PeakMemory(torch.device("cpu"))
    memory.reset()
    before = memory.read_mb()
    # 64 MB of fresh pages, touched: an anonymous mapping, so that no allocator can serve it
    # from memory that earlier tests freed but the process still holds.
    block = mmap.mmap(-1, 64 * 2**20)
    pages = np.frombuffer(block, dtype=np.uint8)
    pages[:] = 1
    after = memory.read_mb()
    del pages
    block.close()
    assert after >= before + 50


ENGINE_KEYS = ("onnxruntime", "openvino", "openvino_int8")


@pytest.mark.slow
def test_bench_times_the_exported_engines(
    tmp_path: Path, cache: Path, capsys: pytest.CaptureFixture
) -> None:
    """Each engine is exported, loaded by its engine and timed; latency is measured, not
    accuracy (random weights), and no timing is asserted."""
    result = _run(
        tmp_path,
        "experiment=smoke",
        "fusion=concat",
        "backbone=resnet18",  # the export path is the same; a small network exports faster
        "--only",
        "peak,infer",
        "--engines",
        "onnxruntime,openvino,openvino-int8",
        *TINY,
    )
    assert list(result["engines"]) == ["torch", "onnxruntime", "openvino", "openvino-int8"]
    assert result["torch_speedup"] == 1.0
    floor = result["infer_floor_s"]
    assert floor == pytest.approx(result["infer_gflop_per_frame"] / result["peak_gflops"])
    for key in ("torch", *ENGINE_KEYS):
        latency, speedup = result[f"{key}_infer_latency_s_median"], result[f"{key}_speedup"]
        assert isinstance(latency, float) and math.isfinite(latency) and latency > 0, key
        assert math.isfinite(speedup) and speedup > 0, key
        assert speedup == pytest.approx(result["infer_latency_s_median"] / latency), key
    engines = result["engines"]
    assert engines["onnxruntime"]["computes"] == "fp32"
    assert engines["openvino"]["computes"] in ("bf16", "fp32")  # bf16 where the CPU has it
    assert engines["openvino-int8"]["computes"].startswith("int8")
    for name in ("onnxruntime", "openvino", "openvino-int8"):
        entry = engines[name]
        assert entry["runs"] == 2 and entry["export_s"] > 0, name
        assert entry["latency_over_floor"] == pytest.approx(entry["latency_s_median"] / floor)
        assert entry["verified_max_rel_diff"] >= 0, name  # verified against PyTorch on export
    printed = capsys.readouterr().out
    assert "| openvino-int8 | int8" in printed and "FLOP floor" in printed


@pytest.mark.parametrize(
    ("engines", "message"),
    [
        ("onnxruntime,onnx-gpu", "--engines onnx-gpu: expected some of torch,onnxruntime,"),
        ("tensorrt", "engine tensorrt needs a CUDA GPU"),
    ],
)
def test_bench_refuses_an_engine_it_cannot_run_in_one_line(
    engines: str, message: str, cache: Path, capsys: pytest.CaptureFixture
) -> None:
    if "tensorrt" in engines and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["experiment=smoke", "--engines", engines])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert message in error
    assert not cache.exists()  # refused before any stage ran


def test_prepare_stage_times_each_fill_and_estimates_the_named_splits(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    result = _run(tmp_path, "--only", "prepare", "--cores", "8")
    stage = result["prepare"]
    assert (stage["height"], stage["width"], stage["cores"]) == (64, 192, 8)
    assert 0 < stage["measured_fraction"] < 0.2  # a lidar's scan lines, not a dense map
    assert list(stage["methods"]) == ["none", "linear", "colorization"]
    for method in stage["methods"].values():
        seconds = method["s_per_frame"]
        assert seconds > 0 and method["frames_per_s_per_worker"] == pytest.approx(1 / seconds)
        for split, frames in benchmarks.NAMED_SPLITS.items():
            assert method["hours"][split] == pytest.approx(frames * seconds / 8 / 3600)
    # The solver against SciPy's spsolve of the same system, on this machine.
    reference = stage["methods"]["colorization"]["spsolve"]
    assert reference["s_per_frame"] > 0 and reference["speedup"] > 0
    assert reference["max_difference_m"] < 0.01  # the 1 cm the fill is held to
    printed = capsys.readouterr().out
    assert "| colorization |" in printed and "h, nuscenes train" in printed
    assert f"colorization: {reference['speedup']:.1f}× SciPy's spsolve" in printed
    assert "infer median" not in printed  # only the stage asked for
    assert "prepare" not in bench.bench_parser().parse_args([]).only.split(",")


def test_prepare_stage_times_the_fill_on_a_prepared_splits_own_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``--prepared`` fills the cached frames' measured depth, cut to each frame's own pixels
    where the cache padded it (frame_box), as prepare filled them."""
    from fusion_depth.data.cache import PreparedFrame, SplitJob, prepare_splits

    rng = np.random.default_rng(0)
    frames = []
    for _ in range(3):
        depth = np.where(rng.random((64, 96)) < 0.05, rng.uniform(2, 60, (64, 96)), 0.0)
        depth[:, 90:] = 0.0  # the padding of a 64x90 frame
        frames.append(
            PreparedFrame(
                image=rng.integers(0, 255, (64, 96, 3), dtype=np.uint8),
                sparse=np.zeros((64, 96), np.float32),
                depth=depth.astype(np.float32),
                condition="day",
                frame_box=(0, 0, 64, 90),
            )
        )
    job = SplitJob(tmp_path, "val", ["a", "b", "c"], lambda i: frames["abc".index(i)], {})
    prepare_splits([job])
    got = benchmarks.prepared_frames(tmp_path / "val", 2)
    assert len(got) == 2 and got[0][0].shape == (64, 90, 3) and got[0][1].shape == (64, 90)
    stored = np.round(frames[1].depth[:, :90] * 256) / 256  # the cache's 1/256 m steps
    np.testing.assert_array_equal(got[1][1], stored)
    result = _run(tmp_path, "--only", "prepare", "--prepared", str(tmp_path / "val"))
    stage = result["prepare"]
    assert (stage["source"], stage["frames"], stage["height"], stage["width"]) == (
        str(tmp_path / "val"),
        3,
        64,
        90,
    )
    assert stage["measured_fraction"] == pytest.approx(
        np.mean([(f.depth[:, :90] > 0).mean() for f in frames])
    )
    assert f"3 frames of {tmp_path / 'val'}" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--prepared", "x"], "--prepared x: times the fill, which --only leaves out"),
        (["--only", "prepare", "--prepared", "missing"], "missing/index.json: not a prepared"),
        (["--only", "prepare", "--frames", "0"], "--frames=0"),
        (["--only", "prepare", "--frames", "2"], "--frames: the frames of a --prepared split"),
        (["--only", "peak,prepare", "--prepared", "missing"], "missing/index.json"),
    ],
)
def test_prepared_frames_are_checked(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch, args, message
) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        bench.main(args)
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
