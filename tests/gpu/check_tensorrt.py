"""The TensorRT back end, checked end to end on a machine with an NVIDIA GPU (CI has none, so
pytest does not collect this file; ``tests/test_export_tensorrt.py`` runs its small GPU test
there too where it can). Run by hand from the repository root, after
``pip install -e ".[dev,tensorrt]"``:

    python tests/gpu/check_tensorrt.py            # smoke size (64×96): a few minutes
    python tests/gpu/check_tensorrt.py --full     # also 384×1248 bench (engine builds take minutes)

It saves an untrained DenseNet-169 ``fusion=concat`` checkpoint of the smoke dataset (as the
tests do), exports it with ``format=tensorrt`` in fp16 and fp32 (each verified against PyTorch
by the exporter, within the README's tolerance), runs each file through ``load_exported`` on a
batch of 3 (chunks of the engine's batch of 1) against the checkpoint, scores the fp16 file with
``python -m fusion_depth.evaluate model_file=...``, checks that ``quantize=int8`` is refused in
one line, and times ``bench --engines torch,tensorrt`` on the GPU (with ``--full`` at 384×1248,
with training throughput and the eager-fp32 baseline). Everything goes to ``--out`` (default a
new temporary folder), with ``summary.json``; any failure raises, so the exit status tells.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]


def _checkpoint(folder: Path) -> Path:
    """An untrained DenseNet-169 concat checkpoint of the smoke dataset, saved as training
    saves one (``tests/conftest.py``'s helper)."""
    from omegaconf import OmegaConf

    from fusion_depth.bench.cli import compose_train_config

    sys.path.insert(0, str(REPO / "tests"))
    from conftest import save_untrained_checkpoint

    dataset = OmegaConf.to_container(
        compose_train_config(["experiment=smoke"]).dataset, resolve=True
    )
    return save_untrained_checkpoint(folder / "concat.ckpt", "concat", dataset)


def _export_and_run(ckpt: Path, folder: Path, precision: str) -> dict[str, Any]:
    import torch

    from fusion_depth.export import export_model, load_exported, sidecar_path
    from fusion_depth.models.inference import predict_depth
    from fusion_depth.runner.checkpoints import load_model

    loaded = load_model(ckpt)
    start = time.perf_counter()
    path = export_model(loaded, "tensorrt", folder / f"concat-{precision}.pt2", precision=precision)
    seconds = time.perf_counter() - start
    sidecar = json.loads(sidecar_path(path).read_text())
    assert sidecar["format"] == "tensorrt" and sidecar["precision"] == precision, sidecar
    exported = load_exported(path).net
    generator = torch.Generator().manual_seed(3)
    height, width = sidecar["inputs"][0]["shape"][2:]
    image = torch.rand(3, 3, height, width, generator=generator)
    returns = torch.rand(3, 1, height, width, generator=generator) < 0.05
    sparse = torch.where(returns, 5 + 60 * torch.rand(returns.shape, generator=generator), 0.0)
    depth = predict_depth(exported, image, sparse)
    reference = predict_depth(loaded.net.float().eval(), image, sparse)
    relative = ((depth - reference).abs() / reference).flatten()
    result = {
        "file": str(path),
        "export_s": seconds,
        "engine": exported.engine,
        "runtime": exported.runner.description,
        "verified": sidecar["verified"],
        "batch3_max_rel_diff": float(relative.max()),
        "batch3_mean_rel_diff": float(relative.mean()),
    }
    print(f"[{precision}] {json.dumps(result, indent=2)}", flush=True)
    assert result["batch3_max_rel_diff"] <= sidecar["verified"]["tolerance"], result
    return result


def _evaluate(model_file: str, folder: Path) -> dict[str, Any]:
    """``python -m fusion_depth.evaluate model_file=...`` as a user runs it."""
    run_dir = folder / "evaluate"
    command = [
        sys.executable,
        "-m",
        "fusion_depth.evaluate",
        f"model_file={model_file}",
        f"hydra.run.dir={run_dir}",
    ]
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=1800)
    if done.returncode:
        raise RuntimeError(f"evaluate failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    metrics = json.loads(next(run_dir.rglob("metrics.json")).read_text())
    print(f"[evaluate] engine {metrics.get('run', {}).get('engine')}", flush=True)
    return metrics


def _int8_is_refused() -> str:
    from fusion_depth.export import check_export_options

    try:
        check_export_options("tensorrt", None, None, None, True, "auto", "int8")
    except ValueError as err:
        assert "\n" not in str(err) and "precision=fp16" in str(err), err
        return str(err)
    raise AssertionError("format=tensorrt quantize=int8 was not refused")


def _bench(folder: Path, full: bool) -> dict[str, Any]:
    from fusion_depth.bench import cli as bench

    # The smoke run skips torch.compile (minutes on a GPU); the full one times the defaults.
    size = ["dataset.height=384", "dataset.width=1248"] if full else ["experiment=smoke"]
    size += [] if full else ["model.compile=false"]
    stages = ["--only", "peak,infer,train", "--baseline"] if full else ["--only", "peak,infer"]
    out = folder / ("bench-full.json" if full else "bench-smoke.json")
    argv = [*size, "trainer.accelerator=gpu", *stages, "--engines", "torch,tensorrt"]
    assert bench.main([*argv, "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    for key in ("torch", "tensorrt"):
        assert result[f"{key}_infer_latency_s_median"] > 0, key
    return {
        key: result.get(key)
        for key in (
            "torch_infer_latency_s_median",
            "tensorrt_infer_latency_s_median",
            "tensorrt_speedup",
            "infer_floor_s",
            "train_samples_per_s",
            "baseline_train_samples_per_s",
            "baseline_infer_latency_s_median",
        )
    } | {"engines": result["engines"], "machine": result["machine"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="where files go (default: a temporary folder)")
    parser.add_argument("--full", action="store_true", help="also bench at 384×1248")
    args = parser.parse_args(argv)
    os.chdir(REPO)
    from fusion_depth.export.runtime import require_tensorrt

    try:
        require_tensorrt("tests/gpu/check_tensorrt.py")
    except ImportError as err:  # no GPU, or no torch-tensorrt: one line, nothing done
        print(err, file=sys.stderr)
        return 2
    folder = args.out or Path(tempfile.mkdtemp(prefix="check-tensorrt-"))
    folder.mkdir(parents=True, exist_ok=True)
    ckpt = _checkpoint(folder)
    summary: dict[str, Any] = {"folder": str(folder)}
    summary["exports"] = {p: _export_and_run(ckpt, folder, p) for p in ("fp16", "fp32")}
    summary["evaluate_engine"] = _evaluate(summary["exports"]["fp16"]["file"], folder).get("run")
    summary["int8_refusal"] = _int8_is_refused()
    summary["bench_smoke"] = _bench(folder, full=False)
    if args.full:
        summary["bench_full"] = _bench(folder, full=True)
    (folder / "summary.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    print(f"all TensorRT checks passed; summary in {folder / 'summary.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
