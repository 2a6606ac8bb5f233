"""Nothing from a checkpoint becomes a callable: crafted checkpoints that name code (a
``_target_`` that walks from an allowed module into one it imports, one nested in the reader's
arguments, one elsewhere in the stored config) are refused by evaluate, predict, export and a
resuming train, naming the key path, and the payload never runs."""

from __future__ import annotations

import copy
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers import compose_config, run_module

from fusion_depth.data.procedural import ProceduralDepth
from fusion_depth.evaluate.scoring import evaluate
from fusion_depth.export.cli import export
from fusion_depth.predict.cli import predict
from fusion_depth.runner.checkpoints import dataset_config, load_model, make_reader
from fusion_depth.train.fit import train
from fusion_depth.utils.checkpoint_file import CONFIG_KEY, RUN_KEY, CheckpointError


def _payload(marker: Path) -> dict:
    """A Hydra node that would create the folder ``marker`` if it were ever instantiated."""
    return {"_target_": "os.makedirs", "name": str(marker)}


def _craft(source: Path, path: Path, kind: str, marker: Path) -> tuple[Path, str]:
    """A copy of the checkpoint ``source`` with a payload of ``kind``; (file, key path)."""
    checkpoint = torch.load(source, weights_only=True)
    config = checkpoint[CONFIG_KEY]
    reader = config["dataset"]["reader"]
    if kind == "prefix walk":  # starts like a reader of this package, then walks into `os`
        reader.update(_target_="fusion_depth.data.procedural.os.makedirs", name=str(marker))
        reader["_partial_"] = False
        where = "dataset.reader._target_"
    elif kind == "nested":  # the reader itself looks plain; one of its arguments is code
        reader["root"] = _payload(marker)
        where = "dataset.reader.root._target_"
    else:  # somewhere nothing reads today
        config["trainer"] = {"plugins": [_payload(marker)]}
        where = "trainer.plugins[0]._target_"
    torch.save(checkpoint, path)
    return path, f"{CONFIG_KEY}.{where}"


KINDS = ("prefix walk", "nested", "elsewhere")


@pytest.fixture
def crafted(checkpoints, tmp_path) -> dict[str, tuple[Path, str]]:
    marker = tmp_path / "pwned"
    files = {
        kind: _craft(checkpoints["rgb"], tmp_path / f"{i}.ckpt", kind, marker)
        for i, kind in enumerate(KINDS)
    }
    yield files
    assert not marker.exists(), "the payload ran"


def _resume_dir(crafted_ckpt: Path, root: Path) -> Path:
    """A run folder whose last.ckpt is the crafted file (what `train` resumes from)."""
    run_dir = root / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    checkpoint = torch.load(crafted_ckpt, weights_only=True)
    checkpoint[RUN_KEY] = {"overrides": ["experiment=smoke"], "wandb_id": "x"}
    torch.save(checkpoint, run_dir / "checkpoints" / "last.ckpt")
    return run_dir


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_every_entry_point_refuses_a_checkpoint_that_names_code(crafted, kind, tmp_path) -> None:
    path, key = crafted[kind]
    out = tmp_path / kind.replace(" ", "_")
    calls = {
        "evaluate": lambda: evaluate(compose_config([f"ckpt_path={path}"], out / "e", "evaluate")),
        "predict": lambda: predict(
            compose_config([f"ckpt_path={path}", "input=split:test"], out / "p", "predict")
        ),
        "export": lambda: export(
            compose_config([f"ckpt_path={path}", "format=torchscript"], out / "x", "export")
        ),
    }
    for name, call in calls.items():
        with pytest.raises(CheckpointError, match=rf"{path}: refused.*{key.replace('[', '.')}"):
            call()
        assert not list((out / name[0]).rglob("*.png")), name  # nothing was predicted
    run_dir = _resume_dir(path, out)
    cfg = compose_config(["experiment=smoke", "logger=none"], run_dir)
    with pytest.raises(CheckpointError, match=rf"last\.ckpt: refused.*{key.replace('[', '.')}"):
        train(cfg)
    assert not (run_dir / "metrics.json").exists()


@pytest.mark.slow
def test_the_command_line_refuses_them_in_one_line(crafted, tmp_path) -> None:
    """As a user runs them: exit status 1 and the one-line refusal naming the key path, for
    each entry point and each kind of payload (round robin)."""
    commands = []
    for i, kind in enumerate(KINDS):
        path, key = crafted[kind]
        commands.append((["fusion_depth.evaluate", f"ckpt_path={path}"], key))
        commands.append((["fusion_depth.export", f"ckpt_path={path}", "format=torchscript"], key))
        if i == 0:
            commands.append(
                (["fusion_depth.predict", f"ckpt_path={path}", "input=split:test"], key)
            )
    path, key = crafted["nested"]
    run_dir = _resume_dir(path, tmp_path)
    commands.append(
        (["fusion_depth.train", "experiment=smoke", "logger=none", f"hydra.run.dir={run_dir}"], key)
    )
    for args, key in commands[:4] + commands[-1:]:
        done: subprocess.CompletedProcess = run_module(args, cwd=tmp_path)
        assert done.returncode == 1, (args, done.stderr[-2000:])
        assert key in done.stderr and "refused" in done.stderr, (args, done.stderr[-2000:])
        assert "Traceback" not in done.stderr, (args, done.stderr[-2000:])


@pytest.mark.slow
def test_the_reader_is_looked_up_by_dataset_name(checkpoints, tmp_path) -> None:
    loaded = load_model(checkpoints["rgb"])
    block = dataset_config(loaded, None)
    assert "_target_" not in block["reader"]  # training stored plain data
    reader = make_reader(block, loaded.path)
    assert reader.func is ProceduralDepth and reader.keywords == block["reader"]

    def crafted(change) -> Path:
        checkpoint = torch.load(checkpoints["rgb"], weights_only=True)
        change(checkpoint[CONFIG_KEY]["dataset"])
        path = tmp_path / f"c{len(list(tmp_path.iterdir()))}.ckpt"
        torch.save(checkpoint, path)
        return path

    unknown = load_model(crafted(lambda d: d.update(name="os")))
    with pytest.raises(CheckpointError, match=r"dataset.name='os' is not one of \['carla'"):
        dataset_config(unknown, None)
    extra = load_model(crafted(lambda d: d["reader"].update(callback="os.system")))
    with pytest.raises(CheckpointError, match=r"dataset.reader.callback is not an argument"):
        make_reader(dataset_config(extra, None), extra.path)
    tensor = crafted(lambda d: d["reader"].update(root=torch.zeros(1)))
    with pytest.raises(CheckpointError, match=r"dataset\.reader\.root \(Tensor\) is not plain"):
        load_model(tensor)


def test_a_pickled_object_is_refused_by_name(checkpoints, tmp_path) -> None:
    checkpoint = copy.deepcopy(torch.load(checkpoints["rgb"], weights_only=True))
    checkpoint["hook"] = subprocess.Popen  # needs full unpickling to rebuild
    torch.save(checkpoint, tmp_path / "pickled.ckpt")
    with pytest.raises(CheckpointError, match=r"refused to load; it holds a subprocess\.Popen"):
        load_model(tmp_path / "pickled.ckpt")


def test_interpolations_and_module_names_in_a_checkpoint_are_never_used(
    checkpoints, tmp_path, monkeypatch
) -> None:
    """An OmegaConf interpolation would run a resolver (``${oc.env:...}`` reads a secret) when a
    config is built from the file; a ``requires.module`` would be imported to check for it."""
    monkeypatch.setenv("FUSION_DEPTH_TEST_SECRET", "hunter2")
    checkpoint = torch.load(checkpoints["rgb"], weights_only=True)
    checkpoint[CONFIG_KEY]["dataset"]["description"] = "${oc.env:FUSION_DEPTH_TEST_SECRET}"
    torch.save(checkpoint, tmp_path / "interpolating.ckpt")
    with pytest.raises(CheckpointError, match=r"an interpolation at fusion_depth_config\.dataset"):
        load_model(tmp_path / "interpolating.ckpt")

    checkpoint = torch.load(checkpoints["rgb"], weights_only=True)
    module = "fusion_depth_test_never_imported"
    checkpoint[CONFIG_KEY]["dataset"]["requires"] = {"module": f"{module}.x", "package": "p"}
    # Where the reader would write: a folder of the file's choosing.
    checkpoint[CONFIG_KEY]["dataset"]["reader"]["root"] = str(tmp_path / "chosen_by_the_file")
    torch.save(checkpoint, tmp_path / "requiring.ckpt")
    imported = []
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a: imported.append(name) or real_find_spec(name, *a),
    )
    (results,) = evaluate(
        compose_config([f"ckpt_path={tmp_path / 'requiring.ckpt'}"], tmp_path / "e", "evaluate")
    )
    assert results["test"]["num_images"] == 5
    assert not [name for name in imported if name.startswith(module)]
    assert not (tmp_path / "chosen_by_the_file").exists()  # this machine's cache was used


def _last_ckpt(run_dir: Path, change) -> Path:
    """A ``last.ckpt`` as train writes it (identity, step, callback states), then changed."""
    folder = run_dir / "checkpoints"
    folder.mkdir(parents=True, exist_ok=True)
    best = folder / "epoch000-rmse9.0000.ckpt"
    best.write_bytes(b"x")
    checkpoint = {
        "state_dict": {},
        "global_step": 3,
        RUN_KEY: {"overrides": ["experiment=smoke"], "wandb_id": "x"},
        "callbacks": {
            "ModelCheckpoint{'monitor': 'val/rmse'}": {
                "dirpath": str(folder),
                "best_model_path": str(best),
                "kth_best_model_path": str(best),
                "best_k_models": {str(best): torch.tensor(9.0)},
            },
            "LastCheckpoint": {"saved_at_step": 3, "pending_log_row": {"step": 2, "x": 1.0}},
        },
    }
    change(checkpoint)
    torch.save(checkpoint, folder / "last.ckpt")
    return folder / "last.ckpt"


def _model_checkpoint_state(checkpoint: dict) -> dict:
    return checkpoint["callbacks"]["ModelCheckpoint{'monitor': 'val/rmse'}"]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda c: c.update({RUN_KEY: "x"}), "fusion_depth_run is not a mapping"),
        (lambda c: c.update(global_step="abc"), "global_step='abc' is not a step count"),
        (lambda c: c.update(callbacks=[1]), "callbacks is not a mapping"),
        (
            lambda c: c["callbacks"]["LastCheckpoint"].update(pending_log_row="x"),
            "callbacks.LastCheckpoint.pending_log_row is not a row",
        ),
        (
            lambda c: c["callbacks"]["LastCheckpoint"].update(pending_log_row={1: 2.0}),
            "callbacks.LastCheckpoint.pending_log_row is not a row",
        ),
    ],
)
def test_a_malformed_training_state_is_refused_in_one_line(tmp_path, change, message) -> None:
    from fusion_depth.runner.resume import plan_start

    run_dir = tmp_path / "run"
    _last_ckpt(run_dir, change)
    with pytest.raises(CheckpointError, match=rf"last\.ckpt: refused; {message}"):
        plan_start(run_dir, run_dir / "checkpoints", "auto", True, ["experiment=smoke"])


def test_a_training_state_cannot_name_files_outside_its_folder(tmp_path) -> None:
    """Lightning deletes the checkpoints a ModelCheckpoint state names once better ones arrive,
    and tests its best one: a crafted state must not point it at any other file."""
    from fusion_depth.runner.resume import plan_start

    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    other_run = tmp_path / "other" / "checkpoints" / "epoch001-rmse1.0000.ckpt"
    run_dir = tmp_path / "run"
    walk_out = str(run_dir / "checkpoints" / ".." / ".." / "victim.txt")
    for target in (walk_out, str(other_run)):

        def point_at(checkpoint: dict, target: str = target) -> None:
            state = _model_checkpoint_state(checkpoint)
            state["best_k_models"] = {target: torch.tensor(1e9)}
            state["best_model_path"] = state["kth_best_model_path"] = target

        _last_ckpt(run_dir, point_at)
        with pytest.raises(CheckpointError, match=r"names '.*', not a file in its folder"):
            plan_start(run_dir, run_dir / "checkpoints", "auto", True, ["experiment=smoke"])
    assert victim.read_text() == "precious"
    # The state train writes is accepted, and its best checkpoint kept.
    last = _last_ckpt(run_dir, lambda c: None)
    start = plan_start(run_dir, run_dir / "checkpoints", "auto", True, ["experiment=smoke"])
    assert start.checkpoint == last and start.pending_log_row == {"step": 2, "x": 1.0}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda c: c.update(deep=_nested(5000)), "nested too deeply"),
        (lambda c: c["dataset"].update(extra=torch.zeros(2)), r"dataset\.extra \(Tensor\)"),
        (lambda c: c["dataset"].update({("a", "b"): 1}), r"dataset\[\('a', 'b'\)\]"),
    ],
)
def test_config_that_is_not_plain_data_is_refused(checkpoints, tmp_path, change, message) -> None:
    checkpoint = torch.load(checkpoints["rgb"], weights_only=True)
    change(checkpoint[CONFIG_KEY])
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(50_000)  # pickling a deep nest needs it; reading it back does not
    try:
        torch.save(checkpoint, tmp_path / "odd.ckpt")
    finally:
        sys.setrecursionlimit(limit)
    with pytest.raises(CheckpointError, match=message):
        load_model(tmp_path / "odd.ckpt")


def _nested(depth: int) -> list:
    value: list = []
    for _ in range(depth):
        value = [value]
    return value


def test_odd_dataset_names_and_run_records_are_refused(checkpoints, tmp_path) -> None:
    checkpoint = torch.load(checkpoints["rgb"], weights_only=True)
    checkpoint[CONFIG_KEY]["dataset"]["name"] = ["procedural"]
    torch.save(checkpoint, tmp_path / "listed.ckpt")
    with pytest.raises(CheckpointError, match=r"dataset.name=\['procedural'\] is not one of"):
        dataset_config(load_model(tmp_path / "listed.ckpt"), None)
    runs = tmp_path / "runs" / "a"
    runs.mkdir(parents=True)
    (runs / "metrics.json").write_text('{"best_checkpoint": 5}')
    with pytest.raises(CheckpointError, match=r"best_checkpoint=5 is not a path"):
        evaluate(compose_config([f"ckpt_path={runs.parent}"], tmp_path / "e", "evaluate"))


def _written(data: bytes):
    return lambda path, source: path.write_bytes(data)


def _state_dict_as(value):
    def write(path: Path, source: Path) -> None:
        checkpoint = torch.load(source, weights_only=True)
        checkpoint["state_dict"] = value
        torch.save(checkpoint, path)

    return write


@pytest.mark.parametrize(
    "write,message",
    [
        (_written(b"hello\n"), "not a readable PyTorch checkpoint"),
        (_written(b"\x80\x02}q"), "not a readable PyTorch checkpoint"),
        (_state_dict_as([torch.zeros(2)]), "state_dict"),
        (_state_dict_as({"net.x": [1, 2]}), "state_dict"),
        (_state_dict_as({1: torch.zeros(2)}), "state_dict"),
    ],
)
def test_a_checkpoint_of_odd_bytes_or_shapes_is_one_line_naming_it(
    checkpoints, tmp_path, write, message
) -> None:
    """A text file (torch.load's unpickler raised KeyError), a cut pickle, and a checkpoint
    whose state_dict is a list, holds a list or has a key that is no name: each is refused in
    one line naming the file, by what evaluate, predict and export load with."""
    path = tmp_path / "odd.ckpt"
    write(path, checkpoints["rgb"])
    with pytest.raises((CheckpointError, ValueError)) as err:
        load_model(path)
    text = str(err.value)
    assert "\n" not in text and str(path) in text and message in text, text
