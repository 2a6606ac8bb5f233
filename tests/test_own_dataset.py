"""The docs' "Add your own dataset" guide (``docs/guides/datasets/own-dataset.md``), run as
written: its module and its YAML are copied out of the page into a temporary folder, and its
commands train, evaluate and prepare on a folder of PNG triplets made here."""

from __future__ import annotations

import json
import os
import re
import shlex
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO, run_module

from fusion_depth.data.depth_io import write_depth_png, write_rgb_png

GUIDE = REPO / "docs" / "guides" / "datasets" / "own-dataset.md"
SMALL = ["experiment=smoke", "trainer.max_epochs=1", "logger=none"]


def _section() -> str:
    return GUIDE.read_text(encoding="utf-8")


def _blocks(section: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", section, flags=re.DOTALL)


def _write_triplets(root: Path, frames: int = 4, size: tuple[int, int] = (80, 200)) -> None:
    """A street-like depth ramp per frame, its image, and 300 of its pixels as the sparse map."""
    h, w = size
    rng = np.random.default_rng(0)
    for split in ("train", "val", "test"):
        for i in range(frames):
            depth = np.linspace(40.0, 3.0, h, dtype=np.float32)[:, None].repeat(w, axis=1)
            depth *= rng.uniform(0.8, 1.2)
            image = (255 * (depth / 50.0))[..., None].repeat(3, axis=2).astype(np.uint8)
            sparse = np.zeros_like(depth)
            keep = rng.choice(h * w, size=300, replace=False)
            sparse.flat[keep] = depth.flat[keep]
            for kind in ("image", "sparse", "depth"):
                (root / split / kind).mkdir(parents=True, exist_ok=True)
            write_rgb_png(root / split / "image" / f"{i:03d}.png", image)
            write_depth_png(root / split / "sparse" / f"{i:03d}.png", sparse)
            write_depth_png(root / split / "depth" / f"{i:03d}.png", depth)


@pytest.fixture(scope="module")
def own_dataset(tmp_path_factory) -> dict:
    """The guide's files in a work folder, a dataset folder, and the environment the guide's
    ``export PYTHONPATH=$PWD/my_datasets`` gives."""
    work = tmp_path_factory.mktemp("own_dataset")
    section = _section()
    (module,) = _blocks(section, "python")
    (config,) = _blocks(section, "yaml")
    name = re.search(r"saved as `my_datasets/(\w+)\.py`", section).group(1)
    (work / "my_datasets").mkdir()
    (work / "my_datasets" / f"{name}.py").write_text(module, encoding="utf-8")
    config_file = re.search(r"its config, `(my_conf/dataset/\w+\.yaml)`", section).group(1)
    (work / config_file).parent.mkdir(parents=True)
    (work / config_file).write_text(config, encoding="utf-8")
    root = work / "triplets"
    _write_triplets(root)
    env = dict(os.environ)
    (export,) = [line for line in _blocks(section, "bash")[0].splitlines() if "export" in line]
    key, value = export.split()[1].split("=", 1)
    env[key] = value.replace("$PWD", str(work))
    commands = [
        shlex.split(line)[1:]  # python -m ... -> -m ...
        for line in _blocks(section, "bash")[0].splitlines()
        if line.startswith("python -m")
    ]
    return {"work": work, "root": root, "env": env, "commands": commands, "name": name}


def _command(args: list[str], root: Path, ckpt: str | None = None) -> list[str]:
    """A guide's command with its placeholders filled in (``-m`` dropped: run_module adds it)."""
    filled = []
    for arg in args[1:]:
        arg = arg.replace("/data/triplets", str(root))
        if ckpt is not None:
            arg = arg.replace("<best>.ckpt", ckpt)
        filled.append(arg)
    return filled


@pytest.mark.slow
def test_the_readme_dataset_trains_evaluates_and_prepares(own_dataset) -> None:
    work, root, env = own_dataset["work"], own_dataset["root"], own_dataset["env"]
    train_args, evaluate_args = own_dataset["commands"]
    assert train_args[1] == "fusion_depth.train" and evaluate_args[1] == "fusion_depth.evaluate"

    before = sorted((p, p.stat().st_mtime_ns) for p in root.rglob("*"))
    trained = run_module(_command(train_args, root) + SMALL, work, env=env)
    assert trained.returncode == 0, trained.stderr[-3000:]
    (record,) = work.glob("outputs/**/metrics.json")
    metrics = json.loads(record.read_text())
    # Every test frame was read from the triplets (4 frames; the smoke run scores 3 batches of 2).
    assert metrics["test"]["num_images"] == 4
    assert np.isfinite(metrics["test"]["rmse"])
    cache = Path(env["FUSION_DEPTH_CACHE"]) / own_dataset["name"]
    (prepared,) = [p for p in cache.iterdir() if p.is_dir()]
    assert sorted(p.name for p in prepared.iterdir() if p.is_dir()) == ["test", "train", "val"]
    assert sorted((p, p.stat().st_mtime_ns) for p in root.rglob("*")) == before  # only read

    best = metrics["best_checkpoint"]
    scored = run_module(_command(evaluate_args, root, best) + ["logger=none"], work, env=env)
    assert scored.returncode == 0, scored.stderr[-3000:]
    assert "rmse" in scored.stdout.lower()


@pytest.mark.slow
def test_a_broken_frame_of_the_readme_dataset_is_named(own_dataset, tmp_path) -> None:
    """A missing sparse map fails training before it starts, naming the file; prepare skips the
    frame and names it."""
    env = own_dataset["env"]
    root = tmp_path / "triplets"
    _write_triplets(root, frames=3)
    missing = root / "val" / "sparse" / "001.png"
    missing.unlink()
    train_args = own_dataset["commands"][0]
    failed = run_module(_command(train_args, root) + SMALL, own_dataset["work"], env=env)
    assert failed.returncode == 1
    assert str(missing) in failed.stderr and "Traceback" not in failed.stderr

    prepare_args = ["fusion_depth.prepare", *_command(train_args, root)[1:]]
    skipped = run_module(prepare_args, own_dataset["work"], env=env)
    assert skipped.returncode == 1
    assert "val/001" in skipped.stdout + skipped.stderr
