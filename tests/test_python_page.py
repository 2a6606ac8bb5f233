"""The Python page (docs/get-started/python.md) runs as written: its ``python`` blocks, in
order, in one namespace, in a folder laid out as the commands leave it (an RGB run's and a
concat run's checkpoint, photos, a radar PNG), with its ``export`` command run in between as a
user would paste it."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import REPO, run_module, save_untrained_checkpoint
from PIL import Image

from fusion_depth.data.depth_io import read_depth_png, write_depth_png
from fusion_depth.models.inference import predict_depth
from fusion_depth.runner.checkpoints import load_model

PAGE = REPO / "docs" / "get-started" / "python.md"
BLOCK = re.compile(r"^```(python|bash)\n(.*?)^```", re.M | re.S)


def _blocks() -> list[tuple[str, str]]:
    blocks = BLOCK.findall(PAGE.read_text())
    # Admonition bodies are indented: the note's train command is not one of the page's steps.
    return [(kind, code) for kind, code in blocks if not code.startswith(" ")]


def _lay_out(root: Path, dataset: dict) -> dict[str, Path]:
    """Checkpoints where `train` and `train fusion=concat` keep them, and inputs."""
    made = {}
    for run, fusion in (("default", "rgb"), ("fusion-concat", "concat")):
        folder = root / "outputs" / run / "checkpoints"
        folder.mkdir(parents=True)
        made[fusion] = save_untrained_checkpoint(
            folder / "epoch003-rmse9.8765.ckpt", fusion, dataset, backbone="resnet18", spread=True
        )
        # A run also keeps last.ckpt: the page picks the best one (here: other weights).
        save_untrained_checkpoint(folder / "last.ckpt", fusion, dataset, 1, "resnet18", True)
    height, width = dataset["height"], dataset["width"]
    rng = np.random.default_rng(0)
    (root / "photos").mkdir()
    for i in range(3):
        pixels = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        Image.fromarray(pixels).save(root / "photos" / f"{i:06d}.png")
    radar = np.zeros((height, width), np.float32)
    radar[rng.integers(0, height, 40), rng.integers(0, width, 40)] = rng.uniform(2, 60, 40)
    (root / "radar").mkdir()
    write_depth_png(root / "radar" / "000000.png", radar)
    return made


@pytest.mark.slow
def test_the_python_page_runs_as_written(
    tmp_path: Path, smoke_dataset: dict, monkeypatch, capsys
) -> None:
    made = _lay_out(tmp_path, smoke_dataset)
    blocks = _blocks()
    assert [kind for kind, _ in blocks] == ["python"] * 4 + ["bash", "python"]
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for kind, code in blocks:
        if kind == "bash":
            joined = code.replace("\\\n", " ").splitlines()
            (command,) = [line for line in joined if line.startswith("python -m")]
            argv = shlex.split(command.replace("<best>", made["rgb"].stem))[2:]
            result = run_module(argv, cwd=tmp_path, timeout=600)
            assert result.returncode == 0, result.stdout + result.stderr
            continue
        exec(compile(code, str(PAGE), "exec"), namespace)  # noqa: S102 - the page's own code

    # What the snippets computed is what the package computes for the same inputs.
    image = np.array(Image.open(tmp_path / "photos" / "000000.png"))
    batch = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255
    rgb, concat = load_model(made["rgb"]).net, load_model(made["concat"]).net
    sparse = torch.from_numpy(read_depth_png(tmp_path / "radar" / "000000.png"))[None, None]
    with torch.no_grad():
        assert torch.equal(namespace["depth"], predict_depth(rgb, batch))
        expected = predict_depth(concat, batch, sparse)
        assert torch.equal(namespace["fused_depth"], expected)
        # The radar changes a fusion model's answer: the page's sparse input reached it.
        assert not torch.equal(expected, predict_depth(concat, batch, torch.zeros_like(sparse)))
    assert namespace["depth"].shape == (1, 1, *image.shape[:2])
    written = sorted(p.name for p in (tmp_path / "depth_maps").iterdir())
    assert written == sorted(p.name for p in (tmp_path / "photos").iterdir())
    for name in written:  # each map is its photo's depth, at 1/256 m
        photo = np.array(Image.open(tmp_path / "photos" / name))
        with torch.no_grad():
            one = predict_depth(rgb, torch.from_numpy(photo).permute(2, 0, 1)[None].float() / 255)
        stored = read_depth_png(tmp_path / "depth_maps" / name)
        assert np.abs(stored - one[0, 0].numpy()).max() <= 0.5 / 256 + 1e-4
    # The exported model answers as the checkpoint does (ONNX Runtime, fp32).
    assert (tmp_path / "deploy" / "depth.onnx").is_file()
    assert namespace["exported"].engine == "onnxruntime"
    assert torch.allclose(namespace["exported_depth"], namespace["depth"], atol=1e-3, rtol=1e-4)
    printed = capsys.readouterr().out
    assert "rgb resnet18" in printed and "3 depth maps in depth_maps/" in printed
