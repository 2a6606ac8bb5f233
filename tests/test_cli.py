"""The command lines as users type them: pasted paths, the README's commands, unknown keys
without ``+``, bad optimizer values, sizes that cannot train, splits that cannot be scored, short
errors and progress lines in a log file."""

from __future__ import annotations

import logging
import os
import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import REPO, run_module
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from PIL import Image

from fusion_depth.config import CONF_DIR, SWEEPS_DIR, check_config_values, validate_config
from fusion_depth.config.hydra_main import unknown_key_message, user_message
from fusion_depth.config.run_dirs import job_subdir, run_dir, run_dirname, sweep_dir
from fusion_depth.errors import ConfigError
from fusion_depth.models import DepthNet
from fusion_depth.runner.callbacks import ProgressLog
from fusion_depth.runner.datamodule import DepthDataModule, check_scorable
from fusion_depth.runner.protocol import EvalProtocol
from fusion_depth.train.fit import train

# --- paths as printed are paths as accepted ---------------------------------------------------

# Hydra's override_dirname of runs, as it joins them: sweeps, paths, lists, quotes, spaces.
OVERRIDE_DIRNAMES = [
    "fusion=concat,loss=l1",
    "fusion=rgb,concat,add,loss=l1,l2,berhu",
    "experiment=smoke,optimizer.lr=1e-4,seed=-1,trainer.max_epochs=3",
    "+dataset.tag=night rain,dataset.root=/data/kitti,eval.max_depth=[50,70,80]",
    "input='a=b.png',hydra.run.dir=${now:%H-%M},x={a: 1}",
]


@pytest.mark.parametrize("override_dirname", OVERRIDE_DIRNAMES)
@pytest.mark.parametrize("key", ["ckpt_path", "input", "hydra.run.dir", "dataset.root", "+x.y"])
def test_a_path_a_run_prints_goes_back_unquoted(key: str, override_dirname: str) -> None:
    name = run_dirname(override_dirname)
    for path in (
        f"outputs/{name}/checkpoints/epoch019-rmse8.1234.ckpt",
        f"multirun/procedural_weather/{name}/{name}/checkpoints/last.ckpt",
        f"/tmp/runs/{name}/predictions",
    ):
        override = OverridesParser.create().parse_override(f"{key}={path}")
        assert override.value() == path
        assert not override.is_sweep_override()


def test_run_folder_names_read_as_their_overrides() -> None:
    assert run_dirname("fusion=concat,loss=l1") == "fusion-concat+loss-l1"
    assert run_dirname("fusion=rgb,concat,loss=l1") == "fusion-rgb+concat+loss-l1"
    assert run_dirname("optimizer.lr=1e-4,+dataset.tag=a b") == "optimizer.lr-1e-4++dataset.tag-a_b"
    assert run_dirname("") == "default"


def test_a_run_folder_of_an_earlier_release_is_found_by_the_same_command(tmp_path) -> None:
    """Folders named before 0.2 (``fusion=concat,loss=l1``) are used when only they exist, so
    the same command resumes or skips them; a folder of the new name wins when both exist."""
    dirname = "fusion=concat,loss=l1"
    outputs = tmp_path / "outputs"
    assert run_dir(str(outputs), dirname) == f"{outputs}/fusion-concat+loss-l1"
    (outputs / dirname).mkdir(parents=True)
    assert run_dir(str(outputs), dirname) == f"{outputs}/{dirname}"
    (outputs / "fusion-concat+loss-l1").mkdir()
    assert run_dir(str(outputs), dirname) == f"{outputs}/fusion-concat+loss-l1"
    # a sweep and its jobs, under a sweep config's name
    multirun = tmp_path / "multirun"
    legacy = multirun / "procedural_weather" / "seed=42,43"
    (legacy / "fusion=concat,seed=42").mkdir(parents=True)
    found = sweep_dir(str(multirun), "procedural_weather", "seed=42,43")
    assert found == str(legacy)
    assert job_subdir(found, "fusion=concat,seed=42") == "fusion=concat,seed=42"
    assert job_subdir(found, "fusion=concat,seed=43") == "fusion-concat+seed-43"
    assert sweep_dir(str(multirun), "train", "seed=1,2") == f"{multirun}/seed-1+2"
    assert sweep_dir(str(multirun), "procedural_weather", "") == f"{multirun}/procedural_weather"
    assert sweep_dir(str(multirun), "train", "") == f"{multirun}/default"


def test_a_path_of_ones_own_with_syntax_in_it_gets_its_quoted_form() -> None:
    from hydra.errors import OverrideParseException

    for override in ("ckpt_path=outputs/fusion=concat,loss=l1/x.ckpt", "input=my runs/a (1).png"):
        with pytest.raises(OverrideParseException) as err:
            OverridesParser.create().parse_overrides([override])
        message = user_message(err.value)
        key, _, value = override.partition("=")
        quoted = f"'{key}=\"{value}\"'"
        assert message.startswith(f"{override}: ") and message.endswith(f"quote it: {quoted}")
        (typed,) = shlex.split(quoted)
        assert OverridesParser.create().parse_override(typed).value() == value


# --- unknown keys, with or without + ----------------------------------------------------------


def _key_error(*overrides: str, config_name: str = "train") -> str:
    GlobalHydra.instance().clear()
    with pytest.raises(Exception) as err, initialize_config_dir(CONF_DIR, version_base="1.3"):
        compose(config_name, overrides=list(overrides), return_hydra_config=True)
    message = unknown_key_message(err.value, list(overrides))
    assert message is not None and "\n" not in message
    return message


def test_unknown_key_without_plus_gets_the_did_you_mean_line() -> None:
    assert _key_error("trainer.max_epoch=3").startswith(
        "trainer.max_epoch: unknown key (did you mean max_epochs?); expected one of"
    )
    assert "did you mean trainer?" in _key_error("trainr.max_epochs=3")
    # a sweep's job, as the launcher composes it (the command line: below), and evaluate's
    assert "did you mean max_epochs?" in _key_error("fusion=rgb", "trainer.max_epoch=3")
    assert "did you mean split?" in _key_error("ckpt_path=x", "splt=val", config_name="evaluate")


def test_a_trainer_argument_the_config_lacks_says_how_to_add_it() -> None:
    assert "add it with +trainer.detect_anomaly=true" in _key_error("trainer.detect_anomaly=true")


def test_other_problems_are_left_to_hydra() -> None:
    GlobalHydra.instance().clear()
    with pytest.raises(Exception) as err, initialize_config_dir(CONF_DIR, version_base="1.3"):
        compose("train", overrides=["fusion=nope"], return_hydra_config=True)
    assert unknown_key_message(err.value, ["fusion=nope"]) is None  # Hydra lists the options
    # Known keys compose; + adds a key, which the config checks judge (test_safety).
    GlobalHydra.instance().clear()
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        compose("train", overrides=["trainer.max_epochs=3", "+trainer.max_epoch=3"])


def test_the_packaged_sweeps_are_found_by_name(packaged_sweeps) -> None:
    GlobalHydra.instance().clear()
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose("procedural_weather", return_hydra_config=True)
    assert cfg.hydra.sweeper.params.fusion == "rgb,concat,add"
    assert Path(SWEEPS_DIR, "procedural_weather.yaml").is_file()


# --- every command of the README and the docs, as written -------------------------------------

# Placeholders the README and the docs use for values the reader fills in.
PLACEHOLDERS = {
    "<best>": "epoch019-rmse8.8491",
    "<ckpt>": "outputs/fusion-concat/checkpoints/epoch019-rmse8.8491.ckpt",
    "<sweep>": "loss_fusion_grid",
    "<name>": "topview",
}
HYDRA_COMMANDS = {"train": "train", "prepare": "prepare", "evaluate": "evaluate",
                  "predict": "predict", "export": "export",
                  "score_sparse": "score_sparse"}  # fmt: skip


DOCUMENTS = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def documented_commands(paths: list[Path] = DOCUMENTS) -> list[str]:
    """Every command line of the README and the docs: the lines of their shell code blocks
    (continuations joined) and the inline ``python -m fusion_depth.<command> ...`` outside
    them."""
    commands = []
    for path in paths:
        block, language = None, ""
        for line in path.read_text().splitlines():
            fence = line.strip()
            if fence.startswith("```"):
                if block is None:
                    block, language = [], fence[3:].strip()
                    continue
                if language in ("", "bash", "sh", "console"):
                    for joined in "\n".join(block).replace("\\\n", " ").splitlines():
                        # --config-dir my_conf: the own-dataset guide's dataset, which needs its
                        # files; tests/test_own_dataset.py writes them and runs those commands.
                        if re.match(r"\s*(python -m fusion_depth\.|fusion-depth-)", joined) and (
                            "--config-dir my_conf" not in joined
                        ):
                            commands.append(joined.strip())
                block = None
            elif block is not None:
                block.append(line)
            elif not line.startswith("#"):  # headings name a command without arguments
                commands += re.findall(
                    r"`((?:python -m fusion_depth\.|fusion-depth-)[^\s`]+ [^`]*)`", line
                )
    return commands


def _argv(command: str) -> tuple[str, list[str]]:
    for placeholder, value in PLACEHOLDERS.items():
        command = command.replace(placeholder, value)
    words = shlex.split(command, comments=True)
    if words[0] == "python":
        module, args = words[2], words[3:]
    else:
        module, args = "fusion_depth." + words[0].removeprefix("fusion-depth-"), words[1:]
    return module.removeprefix("fusion_depth."), args


def test_the_docs_have_commands_for_every_entry_point() -> None:
    modules = {_argv(c)[0] for c in documented_commands()}
    assert set(HYDRA_COMMANDS) | {"report", "bench"} <= modules
    assert {_argv(c)[0] for c in documented_commands([REPO / "README.md"])} >= {"train", "report"}


@pytest.mark.slow
@pytest.mark.parametrize("command", documented_commands())
def test_every_documented_command_parses_and_composes(
    command: str, monkeypatch, tmp_path, packaged_sweeps
) -> None:
    """Each command's arguments go through the command's own parser: Hydra's override grammar
    then composition of the real configs (groups
    and keys exist) and the value checks; report's and bench's argparse options."""
    from hydra._internal.utils import get_args_parser

    module, args = _argv(command)
    if module == "report":
        from fusion_depth.report.cli import _parser

        _parser().parse_args(args)
        return
    if module == "bench":
        from fusion_depth.bench.cli import bench_parser

        args = bench_parser().parse_intermixed_args(args).overrides
        config_name, config_dir = "train", None
    elif module in HYDRA_COMMANDS:
        parsed = get_args_parser().parse_args(args)
        args, config_dir = list(parsed.overrides), parsed.config_dir
        config_name = parsed.config_name or HYDRA_COMMANDS[module]
    else:  # the built-in dataset's preview or test frames as files: run it for real
        from fusion_depth.data.procedural import main

        assert module == "data.procedural", command
        monkeypatch.chdir(tmp_path)
        main(args)
        if "--frames" in args:
            assert (tmp_path / args[args.index("--frames") + 1] / "photos" / "000000.png").is_file()
        else:
            assert (tmp_path / args[args.index("--out") + 1]).is_file()
        return
    overrides = OverridesParser.create().parse_overrides(args)
    single = [
        f"{o.get_key_element()}={next(iter(o.sweep_string_iterator()))}"
        if o.is_sweep_override()
        else o.input_line
        for o in overrides
    ]
    if config_dir:
        assert Path(REPO, config_dir).is_dir() or Path(config_dir).is_dir(), config_dir
        single.append(f"hydra.searchpath=[file://{Path(REPO, config_dir).resolve()}]")
    GlobalHydra.instance().clear()
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose(config_name, overrides=single)
    if HYDRA_COMMANDS.get(module) in ("train", "prepare") or module == "bench":
        if cfg.dataset.get("requires") and cfg.dataset.name == "nuscenes":
            cfg.dataset.requires = None  # the devkit is an optional extra
        if config_name == "prepare":  # it checks the dataset alone (its groups are plain)
            from fusion_depth.config.dataset_validation import check_dataset

            check_dataset(cfg.dataset, cfg.fusion.mode)
        else:
            check_config_values(cfg)


# --- config values checked before training ----------------------------------------------------


@pytest.mark.parametrize(
    "override,message",
    [
        ("optimizer.lr=-1", "optimizer.lr=-1: expected a learning rate > 0"),
        ("optimizer.lr=abc", "optimizer.lr=abc: expected a learning rate > 0"),
        ("optimizer.lr=0", "optimizer.lr=0: expected a learning rate > 0"),
        ("optimizer.betas=[0.9,1.0]", "optimizer.betas=[0.9, 1.0]: expected [beta1, beta2]"),
        ("optimizer.weight_decay=-0.1", "optimizer.weight_decay=-0.1: expected a number ≥ 0"),
        ("scheduler.step_size=0", "scheduler.step_size=0: expected an integer ≥ 1"),
        ("scheduler.gamma=-2", "scheduler.gamma=-2: expected a factor > 0"),
        ("trainer.accumulate_grad_batches=0", "trainer.accumulate_grad_batches=0: expected"),
        ("trainer.val_check_interval=1.5", "trainer.val_check_interval=1.5: expected"),
        ("callbacks.progress_log.every_s=abc", "callbacks.progress_log.every_s=abc: expected"),
    ],
)
def test_optimizer_scheduler_and_trainer_values_are_checked(make_config, override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        validate_config(make_config("experiment=smoke", override))


@pytest.mark.slow
def test_a_one_pixel_bottleneck_at_batch_1_is_refused_and_the_next_size_trains(make_config):
    tiny = ("experiment=smoke", "data.batch_size=1", "dataset.height=32", "dataset.width=32")
    with pytest.raises(ConfigError, match=r"data.batch_size=1 with dataset.height=32, dataset"):
        validate_config(make_config(*tiny))
    # The smallest accepted sizes take a training step: 1×2 at batch 1, 1×1 at batch 2.
    for batch, (h, w) in ((1, (32, 64)), (2, (32, 32))):
        validate_config(
            make_config(
                *tiny[:1], f"data.batch_size={batch}", f"dataset.height={h}", f"dataset.width={w}"
            )  # fmt: skip
        )
        net = DepthNet("densenet169", "concat").train()
        out = net(torch.rand(batch, 3, h, w), torch.rand(batch, 1, h, w))
        out.mean().backward()
        assert torch.isfinite(out).all()


# --- splits that cannot be scored -------------------------------------------------------------


class _Frames(torch.utils.data.Dataset):
    def __init__(self, depths: list[np.ndarray]) -> None:
        self.depths = depths

    def __len__(self) -> int:
        return len(self.depths)

    def __getitem__(self, i: int) -> dict:
        depth = torch.as_tensor(self.depths[i], dtype=torch.float32)[None]
        return {"image": torch.zeros(3, *depth.shape[-2:]), "sparse": torch.zeros_like(depth),
                "depth": depth, "condition": "day"}  # fmt: skip


def _datamodule(depths: list[np.ndarray]) -> DepthDataModule:
    return DepthDataModule(reader=lambda split: _Frames(depths), batch_size=1, eval_batch_size=2)


def test_a_split_without_scorable_ground_truth_is_refused_naming_split_frames_and_crop():
    empty = np.zeros((32, 32))
    top_only = np.zeros((32, 32))
    top_only[:3] = 20.0  # outside the Garg crop (rows 41-99 % of the frame)
    protocol = EvalProtocol.from_config({"crop": "garg"}, 0.1, 80.0)
    with pytest.raises(ConfigError) as err:
        check_scorable(_datamodule([empty, top_only, empty]), protocol, {}, "kitti")
    message = str(err.value)
    assert "the val split cannot be scored: none of the 3 frames" in message
    assert "(indices 0-2)" in message and "eval.crop=garg" in message and "32×32" in message
    assert "dataset.height" in message

    # One scorable pixel anywhere in what the stage reads is enough ...
    scorable = top_only.copy()
    scorable[20, 16] = 5.0
    check_scorable(_datamodule([empty, top_only, scorable]), protocol, {}, "kitti")
    # ... but not in a frame the stage never reads (2 frames per batch, 1 batch).
    with pytest.raises(ConfigError, match="none of the 2 frames its val stage reads"):
        check_scorable(
            _datamodule([empty, top_only, scorable]), protocol, {"limit_val_batches": 1}, "kitti"
        )


def test_training_refuses_an_unscorable_split_before_the_first_step(make_config) -> None:
    cfg = make_config("experiment=smoke", "logger=none", "eval.min_depth=500", "eval.max_depth=600")
    with pytest.raises(ConfigError, match=r"the val split cannot be scored.*\(500, 600\) m"):
        train(cfg)
    assert not list(Path(cfg.paths.output_dir).glob("checkpoints/*.ckpt"))


# --- progress in a log file -------------------------------------------------------------------


def test_training_logs_a_line_per_epoch_and_inside_epochs_without_a_terminal(
    make_config, caplog
) -> None:
    cfg = make_config(
        "experiment=smoke",
        "logger=none",
        "trainer.enable_progress_bar=false",
        "callbacks.progress_log.every_s=1e-9",  # a line after every batch
    )
    with caplog.at_level(logging.INFO, logger="fusion_depth.runner.callbacks"):
        results = train(cfg)
    lines = [r.getMessage() for r in caplog.records if r.name == "fusion_depth.runner.callbacks"]
    epochs = [line for line in lines if re.match(r"epoch \d/2: train loss", line)]
    assert len(epochs) == 2, lines
    first = results["validation"][0]
    assert f"val RMSE {first['rmse']:.3f} m, δ1 {first['delta1']:.3f}" in epochs[0]
    assert "ETA" in epochs[0] and "ETA" not in epochs[1]
    assert any(re.match(r"epoch 1/2: batch 1/3, loss \d", line) for line in lines), lines
    assert any(re.match(r"test: batch 1/3, ETA", line) for line in lines), lines


def test_progress_lines_follow_the_clock(caplog) -> None:
    class FakeTrainer:
        progress_bar_callback = None
        is_global_zero = True
        max_epochs = 4
        current_epoch = 0
        num_training_batches = 10
        callback_metrics = {"train/loss": torch.tensor(0.5)}

        class fit_loop:  # noqa: N801 - the attribute path Lightning has
            class epoch_loop:  # noqa: N801
                class batch_progress:  # noqa: N801
                    class current:  # noqa: N801
                        processed = 0

    now = [0.0]
    callback = ProgressLog(every_s=60, clock=lambda: now[0])
    trainer = FakeTrainer()
    with caplog.at_level(logging.INFO, logger="fusion_depth.runner.callbacks"):
        callback.on_train_epoch_start(trainer, None)
        for batch in range(1, 11):
            now[0] += 25.0
            trainer.fit_loop.epoch_loop.batch_progress.current.processed = batch
            callback.on_train_batch_end(trainer, None)
        callback.on_train_epoch_end(trainer, None)
    lines = [r.getMessage() for r in caplog.records]
    # 250 s of batches: lines at 75 s (batch 3), 150 s (batch 6), 225 s (batch 9), then the epoch.
    assert [line.split(",")[0] for line in lines[:3]] == [
        "epoch 1/4: batch 3/10",
        "epoch 1/4: batch 6/10",
        "epoch 1/4: batch 9/10",
    ]
    assert lines[3] == "epoch 1/4: train loss 0.5000, 4 min, ETA 12 min"


# --- short errors -----------------------------------------------------------------------------


def _topview(root: Path) -> Path:
    rng = np.random.default_rng(0)
    for split, names in {"train": ["a", "b"], "val": ["c"], "test": ["d"]}.items():
        for sub in ("rgb", "depth"):
            (root / split / sub).mkdir(parents=True)
        for name in names:
            rgb = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
            Image.fromarray(rgb).save(root / split / "rgb" / f"{name}.png")
            depth = np.full((64, 96), 3000, dtype=np.uint16)
            Image.fromarray(depth).save(root / split / "depth" / f"{name}.png")
    return root


def _truncate(path: Path) -> Path:
    path.write_bytes(path.read_bytes()[:200])
    return path


def _error_lines(stderr: str) -> list[str]:
    """The lines of stderr that are not Lightning's or W&B's start-up notices."""
    return [line for line in stderr.strip().splitlines() if not line.startswith(_NOTICES)]


# What a run may print to stderr before its error: the seed, W&B's and Lightning's notices.
_NOTICES = ("Seed set to", "wandb:", "Using ", "GPU available", "TPU available", "`Trainer(")


@pytest.mark.slow
def test_a_corrupt_data_file_is_a_short_error_naming_it(tmp_path) -> None:
    bad = _truncate(_topview(tmp_path / "crane data=1") / "train" / "rgb" / "b.png")
    args = [
        "fusion_depth.train",
        "dataset=topview",
        f"dataset.root='{bad.parents[2]}'",  # a folder with '=' in its name, quoted
        "experiment=smoke",
        "logger=none",
        f"hydra.run.dir='{tmp_path / 'run=1'}'",
    ]
    short = run_module(args, cwd=tmp_path)
    assert short.returncode == 1
    lines = _error_lines(short.stderr)
    assert len(lines) == 1 and str(bad) in lines[0], short.stderr
    assert "Traceback" not in short.stderr
    full = run_module(args, cwd=tmp_path, env={**os.environ, "HYDRA_FULL_ERROR": "1"})
    assert full.returncode == 1 and "Traceback" in full.stderr and str(bad) in full.stderr


@pytest.mark.slow
def test_a_run_folder_hydra_cannot_create_is_a_short_error_naming_it(tmp_path) -> None:
    (tmp_path / "afile").write_text("not a folder")
    done = run_module(
        ["fusion_depth.train", "experiment=smoke", f"hydra.run.dir={tmp_path}/afile/run"],
        tmp_path,
    )
    assert done.returncode == 1
    assert f"{tmp_path}/afile/run: Not a directory" in done.stderr.splitlines()
    assert "Traceback" not in done.stderr


@pytest.mark.slow
def test_a_run_folder_on_a_full_disk_is_a_short_error_naming_the_file(tmp_path) -> None:
    """The first file Hydra writes in the run folder goes to a full disk (/dev/full answers
    every write with ENOSPC, as a full file system does): one line naming that file."""
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").symlink_to("/dev/full")
    done = run_module(["fusion_depth.train", "experiment=smoke", f"hydra.run.dir={run}"], tmp_path)
    assert done.returncode == 1
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert lines[0].startswith(f"{run}/.hydra/config.yaml: the disk is full"), done.stderr
    assert "Traceback" not in done.stderr and len(lines) == 1, done.stderr


@pytest.mark.slow
def test_unknown_key_on_the_command_line_is_one_line(tmp_path) -> None:
    done = run_module(["fusion_depth.train", "experiment=smoke", "trainer.max_epoch=3"], tmp_path)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        line for line in done.stderr.strip().splitlines() if line.startswith("trainer.max_epoch")
    ]
    assert "did you mean max_epochs?" in done.stderr
    assert not (tmp_path / "outputs").exists()
    sweep = ["fusion_depth.train", "-m", "experiment=smoke", "fusion=rgb,concat"]
    done = run_module([*sweep, "trainer.max_epoch=3"], tmp_path)
    assert done.returncode == 1
    assert done.stderr.strip().startswith("trainer.max_epoch: unknown key (did you mean max_ep")


@pytest.mark.slow
def test_a_corrupt_file_read_in_a_loader_worker_is_a_short_error_naming_it(tmp_path) -> None:
    """A file that breaks after preparing (here: the prepared cache's copy) is read inside a
    DataLoader worker process, whose error torch re-raises wrapped in the worker's traceback."""
    root = _topview(tmp_path / "crane")
    cache = tmp_path / "cache"
    env = {**os.environ, "FUSION_DEPTH_CACHE": str(cache)}
    base = ["dataset=topview", f"dataset.root={root}", "experiment=smoke", "logger=none"]
    prepared = run_module(["fusion_depth.prepare", *base], cwd=tmp_path, env=env)
    assert prepared.returncode == 0, prepared.stderr
    (bad,) = cache.rglob("train/000001.image.npy")
    # Garbled at its own size: loading a split checks each array's size, not its bytes (a
    # truncated one would be prepared again), so the damage is found when the frame is read.
    bad.write_bytes(b"garbage!" * 25 + bad.read_bytes()[200:])
    args = ["fusion_depth.train", *base, "data.num_workers=1", f"hydra.run.dir={tmp_path / 'r'}"]
    done = run_module(args, cwd=tmp_path, env=env)
    assert done.returncode == 1
    lines = _error_lines(done.stderr)
    assert len(lines) == 1 and str(bad) in lines[0], done.stderr
    assert "DataLoader worker" not in done.stderr and "Traceback" not in done.stderr


@pytest.mark.slow
def test_a_sweep_job_with_a_corrupt_file_fails_in_one_line_and_the_others_run(tmp_path) -> None:
    good = _topview(tmp_path / "good")
    bad = _topview(tmp_path / "bad")
    broken = _truncate(bad / "train" / "rgb" / "b.png")
    done = run_module(
        [
            "fusion_depth.train",
            "-m",
            "dataset=topview",
            f"dataset.root={good},{bad}",
            "experiment=smoke",
            "logger=none",
            f"hydra.sweep.dir={tmp_path / 'sweep'}",
        ],
        tmp_path,
    )
    assert done.returncode == 1
    output = done.stdout + done.stderr
    assert f"job failed: {broken}: unreadable image" in output
    assert "Traceback" not in output
    assert "1 ok, 1 failed" in output
