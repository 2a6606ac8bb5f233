"""The Python page (docs/get-started/python.md) runs as written: its ``python`` blocks, in
order, in one namespace, in a folder laid out as the commands leave it (an RGB run's and a
concat run's checkpoint, and a photo of a user's own), with its commands (the built-in test
frames written as PNGs, the export) run in between as a user would paste them. Without a
checkpoint its first step says which folder it looked in."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import REPO, run_module, save_untrained_checkpoint
from PIL import Image

from fusion_depth.data.depth_io import read_depth_png, read_rgb
from fusion_depth.data.procedural import DATASET_FRAMES, ProceduralDepth
from fusion_depth.models.inference import predict_depth
from fusion_depth.runner.checkpoints import load_model

PAGE = REPO / "docs" / "get-started" / "python.md"
BLOCK = re.compile(r"^```(python|bash)\n(.*?)^```", re.M | re.S)


def _blocks() -> list[tuple[str, str]]:
    blocks = BLOCK.findall(PAGE.read_text())
    # Admonition bodies are indented: the note's train command is not one of the page's steps.
    return [(kind, code) for kind, code in blocks if not code.startswith(" ")]


def _lay_out(root: Path, dataset: dict) -> dict[str, Path]:
    """Checkpoints where `train` and `train fusion=concat` keep them, and a JPEG photo of a
    user's own, of another size than the built-in frames the page's command writes beside it."""
    made = {}
    for run, fusion in (("default", "rgb"), ("fusion-concat", "concat")):
        folder = root / "outputs" / run / "checkpoints"
        folder.mkdir(parents=True)
        made[fusion] = save_untrained_checkpoint(
            folder / "epoch003-rmse9.8765.ckpt", fusion, dataset, backbone="resnet18", spread=True
        )
        # A run also keeps last.ckpt: the page picks the best one (here: other weights).
        save_untrained_checkpoint(folder / "last.ckpt", fusion, dataset, 1, "resnet18", True)
    (root / "photos").mkdir()
    pixels = np.random.default_rng(0).integers(0, 256, (375, 1242, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(root / "photos" / "street.JPG")  # KITTI's size
    return made


def _run_command(code: str, root: Path, made: dict[str, Path]) -> None:
    """The ``python -m`` line of a bash block, run as pasted (``<best>``: the best checkpoint)."""
    joined = code.replace("\\\n", " ").splitlines()
    (command,) = [line for line in joined if line.startswith("python -m")]
    argv = shlex.split(command.replace("<best>", made["rgb"].stem))[2:]
    result = run_module(argv, cwd=root, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.slow
def test_the_python_page_runs_as_written(
    tmp_path: Path, smoke_dataset: dict, monkeypatch, capsys
) -> None:
    made = _lay_out(tmp_path, smoke_dataset)
    blocks = _blocks()
    assert [kind for kind, _ in blocks] == ["bash"] + ["python"] * 4 + ["bash", "python"]
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for kind, code in blocks:
        if kind == "bash":
            _run_command(code, tmp_path, made)
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
    # The page's command wrote the built-in frames (64 × 192) beside the user's JPEG.
    photos = sorted((tmp_path / "photos").iterdir())
    assert [p.name for p in photos] == [f"{i:06d}.png" for i in range(5)] + ["street.JPG"]
    assert image.shape == (DATASET_FRAMES["height"], DATASET_FRAMES["width"], 3)
    written = sorted(p.name for p in (tmp_path / "depth_maps").iterdir())
    assert written == sorted(f"{p.stem}.png" for p in photos)  # JPEGs too
    for photo in photos:  # each map is its photo's depth, at 1/256 m, at the photo's size
        pixels = torch.tensor(read_rgb(photo)).permute(2, 0, 1)[None].float() / 255
        with torch.no_grad():
            one = predict_depth(rgb, pixels)
        stored = read_depth_png(tmp_path / "depth_maps" / f"{photo.stem}.png")
        assert np.abs(stored - one[0, 0].numpy()).max() <= 0.5 / 256 + 1e-4
    # The exported model takes its own size (the checkpoint's dataset's, 64 × 96 here): the
    # page resizes the photo to it, and the model answers as the checkpoint does (ONNX Runtime).
    assert (tmp_path / "deploy" / "depth.onnx").is_file()
    exported = namespace["exported"]
    assert exported.engine == "onnxruntime"
    size = (smoke_dataset["height"], smoke_dataset["width"])
    assert (exported.info.height, exported.info.width) == size != image.shape[:2]
    assert namespace["exported_depth"].shape == (1, 1, *size)
    expected = namespace["torch_depth"]
    assert torch.allclose(namespace["exported_depth"], expected, atol=1e-3, rtol=1e-4)
    printed = capsys.readouterr().out
    assert "rgb resnet18" in printed and "6 depth maps in depth_maps/" in printed


def test_the_python_page_names_the_folder_without_a_checkpoint(tmp_path: Path, monkeypatch) -> None:
    """Before any training, the page's first step fails in one line naming the folder it
    looked in and the command that fills it, not with a bare StopIteration."""
    first = next(code for kind, code in _blocks() if kind == "python")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError) as caught:
        exec(compile(first, str(PAGE), "exec"), {})  # noqa: S102 - the page's own code
    message = str(caught.value)
    assert "outputs/default/checkpoints" in message and "python -m fusion_depth.train" in message
    assert "\n" not in message


def test_the_sample_frames_are_the_built_in_test_frames(tmp_path: Path) -> None:
    """``python -m fusion_depth.data.procedural --frames DIR``, the page's sample inputs, writes
    the first test frames a default run scores (the built-in dataset's settings, which
    conf/dataset/procedural.yaml gives): the same images and the same radar, as PNGs."""
    import yaml

    from fusion_depth.data.procedural import main

    conf = yaml.safe_load((REPO / "conf" / "dataset" / "procedural.yaml").read_text())
    reader = conf["reader"]
    assert DATASET_FRAMES == {
        "height": conf["height"],
        "width": conf["width"],
        "radar_height_extension": reader["radar_height_extension"],
        "seed": reader["seed"],
    }
    assert reader["sparse"] == "radar" and conf["conditions"][:3] == ["day", "night", "fog"]
    main(["--frames", str(tmp_path / "samples"), "--count", "3"])
    dataset = ProceduralDepth(
        "test", tmp_path / "cache", num_test=3, conditions=conf["conditions"], **DATASET_FRAMES
    )
    assert sorted(p.name for p in (tmp_path / "samples" / "photos").iterdir()) == [
        f"{i:06d}.png" for i in range(3)
    ]
    for i in range(3):
        sample = dataset[i]
        image = np.array(Image.open(tmp_path / "samples" / "photos" / f"{i:06d}.png"))
        stored = (sample["image"].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        assert np.array_equal(image, stored)
        radar = read_depth_png(tmp_path / "samples" / "radar" / f"{i:06d}.png")
        assert np.array_equal(radar, sample["sparse"][0].numpy()) and (radar > 0).any()


def test_the_python_page_says_what_to_feed_it() -> None:
    """The page says where images to try come from (the command above, run in the page's own
    test), that a model of the built-in scenes means nothing on a real photo, that JPEGs are
    read too, and that an exported model takes one size (the resize its test runs)."""
    text = PAGE.read_text()
    assert "python -m fusion_depth.data.procedural --frames ." in text
    warning = text.split('!!! warning "', 1)[1].split("\n\n", 1)[0]
    assert "real photo" in warning and "means nothing" in warning
    assert '".jpg"' in text and '".jpeg"' in text
    exported = text.split("## An exported model", 1)[1]
    assert exported.index(".resize(") < exported.index("predict_depth(exported")
