"""The docs' "Add your own model" guide (``docs/guides/own-model.md``), followed as written: its
module and its YAML are copied out of the page into a copy of the checkout (the guide's files go
inside the package), and its commands compose, train under ``experiment=smoke``, evaluate and
export to ONNX. The guide says how many files a model takes; this counts them."""

from __future__ import annotations

import os
import re
import shlex
import shutil
from pathlib import Path

import pytest
import yaml
from helpers import REPO, run_module

GUIDE = REPO / "docs" / "guides" / "own-model.md"


def _blocks(text: str, language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```", text, flags=re.DOTALL | re.MULTILINE)


def _section(text: str, title: str) -> str:
    start = text.index(f"## {title}")
    end = text.find("\n## ", start + 1)
    return text[start : end if end != -1 else None]


@pytest.fixture(scope="module")
def checkout(tmp_path_factory) -> Path:
    """A copy of the checkout (package, configs, sweeps) with the guide's two files added where
    it says, and nothing else changed."""
    root = tmp_path_factory.mktemp("own_model")
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for part in ("fusion_depth", "conf", "sweeps"):
        shutil.copytree(REPO / part, root / part, ignore=ignore)
    text = GUIDE.read_text(encoding="utf-8")
    (module,) = _blocks(_section(text, "Step 1: the network"), "python")
    model_yaml = _blocks(_section(text, "Step 3: the config"), "yaml")[0]
    saved_as = re.search(r"Save it as `(fusion_depth/models/\w+\.py)`", text).group(1)
    config_at = re.search(r"^`(conf/model/\w+\.yaml)`:$", text, flags=re.MULTILINE).group(1)
    (root / saved_as).write_text(module, encoding="utf-8")
    (root / config_at).write_text(model_yaml, encoding="utf-8")
    return root


def _run(command: str, cwd: Path, name: str = "fpn_depth"):
    args = shlex.split(command.replace("<name>", name))
    assert args[:2] == ["python", "-m"], command
    env = {**os.environ, "PYTHONPATH": str(cwd), "WANDB_MODE": "disabled"}
    if args[2] == "fusion_depth.train" and "--cfg" not in args:
        args.append("logger=none")  # as the other command tests: no W&B run
    return run_module(args[2:], cwd, env=env)


def test_the_guide_says_two_files_and_names_two() -> None:
    text = GUIDE.read_text(encoding="utf-8")
    assert "A model is two files" in text.split("\n## ")[0]
    assert re.findall(r"Save it as `(fusion_depth/models/\w+\.py)`", text) == [
        "fusion_depth/models/fpn_depth.py"
    ]
    assert re.findall(r"^`(conf/\S+\.yaml)`:$", text, flags=re.MULTILINE) == [
        "conf/model/fpn_depth.yaml"
    ]


@pytest.mark.slow
def test_a_model_added_as_the_guide_says_composes_trains_evaluates_and_exports(checkout) -> None:
    commands = _blocks(_section(GUIDE.read_text(encoding="utf-8"), "Step 4"), "text")[0]
    compose, smoke, _full, evaluate, export = commands.strip().splitlines()
    assert "--cfg job" in compose and "experiment=smoke" in smoke
    # The copy is the one that runs (its fusion_depth/ comes first on the path), and it is the
    # guide's model: its module and YAML are the only files added.
    added = {
        str(p.relative_to(checkout))
        for part in ("fusion_depth", "conf")
        for p in (checkout / part).rglob("*")
        if p.is_file() and not (REPO / p.relative_to(checkout)).exists()
    }
    assert added == {"fusion_depth/models/fpn_depth.py", "conf/model/fpn_depth.yaml"}

    composed = _run(compose, checkout)
    assert composed.returncode == 0, composed.stderr[-3000:]
    job = yaml.safe_load(composed.stdout)
    assert job["model"]["net"]["name"] == "fpn_depth"  # its recipe's encoder, unless a dataset's
    assert job["backbone"]["name"] == "resnet18"

    trained = _run(smoke, checkout)
    assert trained.returncode == 0, trained.stderr[-3000:]
    (run,) = [p for p in (checkout / "outputs").iterdir() if "model-fpn_depth" in p.name]
    (best,) = sorted((run / "checkpoints").glob("epoch*.ckpt"))[-1:]
    where = f"{run.relative_to(checkout)}/checkpoints/{best.name}"
    folder = "outputs/fusion-concat+model-<name>/checkpoints/<best>.ckpt"

    evaluated = _run(evaluate.replace(folder, where), checkout)
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    assert "rmse" in (evaluated.stdout + evaluated.stderr).lower()

    exported = _run(export.replace(folder, where), checkout)
    assert exported.returncode == 0, exported.stderr[-3000:]
    assert (checkout / "fpn_depth.onnx").stat().st_size > 10_000

    # Step 5: the class's ARGUMENT_RULES refuse a bad value of its own before any work
    refused = _run(f"{smoke} model.net.width=0", checkout)
    assert refused.returncode == 1
    assert "model.net.width=0: expected an integer ≥ 1" in refused.stderr, refused.stderr[-2000:]


def test_a_recipe_naming_a_loss_that_does_not_exist_is_one_line() -> None:
    import dataclasses

    from fusion_depth.config.recipes import model_options
    from fusion_depth.errors import ConfigError
    from fusion_depth.models import MODELS

    entry = MODELS["radarnet"]
    wrong = dataclasses.replace(entry, recipe=dataclasses.replace(entry.recipe, loss="l3"))
    with pytest.raises(ConfigError, match=r"model=radarnet: its Recipe's loss='l3'; expected one"):
        model_options("radarnet", wrong)


def test_a_dataset_recipe_that_does_more_than_switch_groups_is_one_line() -> None:
    """A dataset's recipe is read as data for the default run: its defaults list may only switch
    the four groups a recipe sets."""
    from pathlib import Path

    from fusion_depth.config.recipes import _switched
    from fusion_depth.errors import ConfigError

    recipe = Path("kitti_densedepth.yaml")
    assert _switched(recipe, {"defaults": [{"override /loss": "l2"}]}) == {"loss": "l2"}
    for entry in ("/dataset/kitti", {"override /trainer": "gpu"}, {"override /loss": 3}):
        with pytest.raises(ConfigError, match=r"kitti_densedepth.yaml: defaults entry .*only"):
            _switched(recipe, {"defaults": [entry]})
