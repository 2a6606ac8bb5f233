"""Scoring a checkpoint, a folder of training runs or an exported model file on a dataset split
by the ``eval`` protocol, as ``python -m fusion_depth.evaluate`` does (:mod:`.cli`).

The model is rebuilt from the checkpoint (weights-only loading, see
:mod:`fusion_depth.runner.checkpoints`) or loaded by its sidecar and run by its engine
(:mod:`fusion_depth.export.runtime`), and scored; ``metrics.json`` and ``per_image.csv`` are
written in the same format as a training run's, so ``report`` reads both. The record's
``run.engine`` says what ran the network (``torch`` for a checkpoint, e.g. ``openvino-int8``
for an exported file), so ``report --compare engine=torch`` pairs an exported model with its
checkpoint on the same images.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import Dataset

from fusion_depth.config.dataset_validation import check_dataset
from fusion_depth.data import SPLITS
from fusion_depth.data.depth_io import DEPTH_PNG_SCALE
from fusion_depth.errors import ConfigError
from fusion_depth.export.runtime import ExportedModel, check_source, engine_identity, load_exported
from fusion_depth.models.alignment import FallbackCount
from fusion_depth.models.depth_prior import NO_PRIOR, oracle_prior
from fusion_depth.models.prior_alignment import GlobalAlignment, prior_alignment_config
from fusion_depth.models.released import RELEASED, build_released, record_model_name
from fusion_depth.runner.callbacks import ProgressLog
from fusion_depth.runner.checkpoints import LoadedModel, dataset_config, load_model, make_reader
from fusion_depth.runner.datamodule import DepthDataModule, check_scorable
from fusion_depth.runner.loggers import closing
from fusion_depth.runner.module import DepthModule
from fusion_depth.runner.protocol import EvalProtocol
from fusion_depth.runner.record import (
    METRICS_FILE,
    RunRecord,
    publish_results,
    read_run_record,
    rescored_identity,
)
from fusion_depth.runner.run_folder import RESOLVED_CONFIG_FILE
from fusion_depth.runner.speed import PRECISIONS, accelerator_device, resolve_precision
from fusion_depth.utils.atomic import write_text_atomic
from fusion_depth.utils.checkpoint_file import CheckpointError

log = logging.getLogger(__name__)


def evaluation_precision(requested: str, loaded: LoadedModel, accelerator: str) -> str:
    """``checkpoint`` (evaluate's default): the precision the run trained and was tested in,
    so a re-score reproduces its test stage; ``auto`` where it recorded none or where that
    precision needs a GPU this machine lacks. Any other value as for training."""
    device = accelerator_device(accelerator)
    if requested == "checkpoint":
        trained = (loaded.config.get("trainer") or {}).get("precision")
        usable = trained in PRECISIONS and not (trained == "16-mixed" and device.type != "cuda")
        requested = trained if usable else "auto"
    return resolve_precision(requested, device)


def _guards(cfg: DictConfig) -> dict[str, str | None]:
    """The optional ``fusion=``/``backbone=`` guards of ``cfg``."""
    return {
        "fusion": cfg.fusion.mode if cfg.get("fusion") else None,
        "backbone": cfg.backbone.name if cfg.get("backbone") else None,
    }


def _given_prior(cfg: DictConfig) -> dict | None:
    """The ``prior=`` node given (``prior=none`` included); None where none was."""
    prior = cfg.get("prior")
    return None if prior is None else OmegaConf.to_container(prior, resolve=True)


def _chosen_prior(cfg: DictConfig) -> dict | None:
    """The ``prior=`` node given, where it names a prior (None: none given, or ``prior=none``)."""
    prior = _given_prior(cfg)
    return None if prior is None or prior.get("name") in (None, NO_PRIOR) else prior


def evaluate_alignment(cfg: DictConfig, output_dir: str | Path) -> RunRecord:
    """Score the global alignment of the prior ``cfg.prior`` (no checkpoint: nothing is
    learned) on ``cfg.dataset``, fitted by ``cfg.alignment``; writes ``metrics.json`` (with
    ``alignment``: its settings, fits and fallbacks) and ``per_image.csv`` into
    ``output_dir`` and returns the record written.

    Raises:
        ConfigError: no ``dataset=`` was chosen.
        ArgumentError: the prior cannot be built from ``prior.weights``, or an ``alignment``
            setting is out of range.
    """
    if cfg.split not in SPLITS:
        raise ValueError(f"split={cfg.split!r}: expected one of {list(SPLITS)}")
    prior = _chosen_prior(cfg)
    if cfg.get("dataset") is None or "reader" not in cfg.dataset:
        raise ConfigError(
            f"prior={prior['name']} with no ckpt_path scores the prior's global alignment: "
            "choose the dataset to fit and score it on with dataset=<name>"
        )
    settings = OmegaConf.to_container(cfg.alignment, resolve=True)
    target = settings.pop("target", "sparse")
    if target not in ALIGNMENT_TARGETS:
        raise ConfigError(
            f"alignment.target={target}: expected one of {', '.join(ALIGNMENT_TARGETS)}"
        )
    net = GlobalAlignment(
        prior, **settings, min_depth=cfg.dataset.min_depth, max_depth=cfg.dataset.max_depth
    )
    config = {
        "model": {"net": prior_alignment_config(prior, settings)},
        "fusion": {"mode": net.fusion.mode},
        "backbone": {"name": prior["name"]},  # what computes the depth: the prior's network
        "dataset": OmegaConf.to_container(cfg.dataset, resolve=True),
        "seed": cfg.seed,
    }
    weights = prior.get("weights")  # none for prior=oracle (the ground truth) and prior=zero
    loaded = LoadedModel(
        net=net.eval(),
        config=config,
        path=Path(weights) if weights else None,
        key="prior.weights",
    )
    # What the fit is, in the record's overrides: report keeps each setting its own row.
    fit = {**settings, "target": target}
    if not fit["ransac_iterations"]:
        fit.pop("ransac_threshold")
    served = [f"alignment.{key}={value}" for key, value in fit.items()]
    frames = GroundTruthAsSparse if target == "ground_truth" else None
    if prior["name"] == "oracle":  # the frames bring their prior: their own ground truth
        if frames is not None:
            raise ConfigError(
                "prior=oracle with alignment.target=ground_truth fits the ground truth to "
                "itself; give one of them"
            )
        frames = OracleAsPrior
    return evaluate_loaded(cfg, loaded, output_dir, served=served, frames=frames)


def evaluate_released(cfg: DictConfig, output_dir: str | Path) -> RunRecord:
    """Score a published method's released checkpoint (``released=<name>``, built from its
    authors' files by :func:`~fusion_depth.models.released.build_released`) on ``cfg.dataset``;
    writes ``metrics.json`` and ``per_image.csv`` into ``output_dir`` and returns the record
    written. It runs in fp32 (as its authors' code), whatever the machine supports.

    Raises:
        ConfigError: no ``dataset=`` was chosen, or ``ckpt_path``/``model_file``/``prior`` was
            given too.
        ArgumentError: a released file is missing or is not that network as released (naming
            the ``released.`` key).
    """
    if cfg.split not in SPLITS:
        raise ValueError(f"split={cfg.split!r}: expected one of {list(SPLITS)}")
    settings = OmegaConf.to_container(cfg.released, resolve=True)
    given = [k for k in ("ckpt_path", "model_file") if cfg.get(k) is not None]
    if given or _given_prior(cfg) is not None:
        other = f"{given[0]}=" if given else "prior="
        raise ConfigError(
            f"released={settings['name']} with {other}: a released model is scored from its "
            "authors' files alone; give one of released=, ckpt_path=, model_file="
        )
    if cfg.get("dataset") is None or "reader" not in cfg.dataset:
        raise ConfigError(
            f"released={settings['name']} scores its authors' checkpoint: choose the frames with "
            "dataset=nuscenes (prepared here) or dataset=radarnet_layout (their setup's files)"
        )
    net = build_released(settings)
    name = record_model_name(settings["name"])
    config = {
        "model": {"net": {**settings, "name": name}},
        "fusion": {"mode": net.fusion.mode},
        "backbone": {"name": name},  # its authors' own encoders
        "dataset": OmegaConf.to_container(cfg.dataset, resolve=True),
        "seed": cfg.seed,
        "trainer": {"precision": "32-true"},  # as their code runs it: bf16 moves its depths
    }
    first = RELEASED[settings["name"]].arguments[0]  # the file the record names
    loaded = LoadedModel(
        net=net, config=config, path=Path(settings[first]), key=f"released.{first}"
    )
    return evaluate_loaded(cfg, loaded, output_dir)


# alignment.target: fit each frame to its sparse returns (what a deployed model has), or to its
# own ground truth: the prior's ceiling, as relative depth models are scored (MiDaS, Ranftl et
# al., TPAMI 2022, Sec. 5), not a result a model could reach without the ground truth.
ALIGNMENT_TARGETS = ("sparse", "ground_truth")


class OracleAsPrior(Dataset):
    """A split whose samples carry ``prior``: their ground truth made a perfect relative prior
    (:func:`~fusion_depth.models.depth_prior.oracle_prior`), which the global alignment takes
    in place of running its prior: ``evaluate prior=oracle``."""

    def __init__(self, frames: Dataset) -> None:
        self.frames = frames
        if hasattr(frames, "encoded_sample"):
            self.encoded_sample = lambda index: self._add(frames.encoded_sample(index))

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> dict:
        return self._add(self.frames[index])

    @staticmethod
    def _add(sample: dict) -> dict:
        depth = sample["depth"]
        if depth.dtype == torch.uint16:  # the stored form: 1/256 m
            depth = depth.to(torch.int32).float() / DEPTH_PNG_SCALE
        return {**sample, "prior": oracle_prior(depth)}


class GroundTruthAsSparse(Dataset):
    """A split whose samples carry their ground truth as the sparse input too (the encoded or
    float form, as the split serves it), and no radar points: what
    ``alignment.target=ground_truth`` fits to, pixel by pixel."""

    def __init__(self, frames: Dataset) -> None:
        self.frames = frames
        if hasattr(frames, "encoded_sample"):
            self.encoded_sample = lambda index: self._swap(frames.encoded_sample(index))

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> dict:
        return self._swap(self.frames[index])

    @staticmethod
    def _swap(sample: dict) -> dict:
        swapped = {**sample, "sparse": sample["depth"]}
        swapped.pop("radar_points", None)  # else the fit would sample the radar's returns
        return swapped


def evaluate_checkpoint(
    cfg: DictConfig, ckpt_path: str | Path, output_dir: str | Path
) -> RunRecord:
    """Score one checkpoint; writes ``metrics.json`` and ``per_image.csv`` into ``output_dir``
    and returns the record written."""
    if cfg.split not in SPLITS:
        raise ValueError(f"split={cfg.split!r}: expected one of {list(SPLITS)}")
    prior = _given_prior(cfg)
    loaded = load_model(ckpt_path, **_guards(cfg), prior=prior)
    # Served without the prior it was trained with: another computation, named in its identity.
    without = prior is not None and prior["name"] == NO_PRIOR and _trained_prior(loaded) != NO_PRIOR
    return evaluate_loaded(cfg, loaded, output_dir, served=["prior=none"] if without else [])


def _trained_prior(loaded: LoadedModel) -> str:
    """The prior a checkpoint's network was trained with (``none`` for none)."""
    return ((loaded.config["model"]["net"].get("prior") or {}).get("name")) or NO_PRIOR


def evaluate_model_file(
    cfg: DictConfig, model_file: str | Path, output_dir: str | Path
) -> RunRecord:
    """Score an exported model file (``model_file=``), run by the engine its sidecar names;
    writes ``metrics.json`` and ``per_image.csv`` into ``output_dir`` and returns the record.

    Raises:
        SidecarError: the sidecar is missing or has a bad key (naming the file and key).
        CheckpointError: the sidecar records no dataset and no ``dataset=`` was given.
    """
    if cfg.split not in SPLITS:
        raise ValueError(f"split={cfg.split!r}: expected one of {list(SPLITS)}")
    if _given_prior(cfg) is not None:
        raise ConfigError(
            f"prior={cfg.prior.name} with model_file={model_file}: an exported file holds its "
            "prior; prior= goes with ckpt_path=, or alone to score the prior's alignment"
        )
    return evaluate_loaded(cfg, load_exported(model_file, **_guards(cfg)), output_dir)


def _split_reader(
    block: dict, chosen: dict | None, loaded: LoadedModel, frames: Callable | None
) -> Callable[..., Dataset]:
    """The reader of the dataset ``block`` (built from the package's table of readers, also for
    a block from the checkpoint or sidecar), each split it reads wrapped by ``frames``."""
    read = make_reader(block, None if chosen is not None else loaded.path, loaded.key)
    if frames is None:
        return read

    def reader(**kwargs: Any) -> Dataset:
        return frames(read(**kwargs))

    return reader


def _evaluation_trainer(
    cfg: DictConfig, loaded: LoadedModel, output_dir: Path, logger: Any
) -> L.Trainer:
    """The Trainer that tests ``loaded``: an exported file runs on the CPU, in its engine's
    precision (so the Trainer's is fp32); a checkpoint in :func:`evaluation_precision`."""
    exported = isinstance(loaded.net, ExportedModel)
    progress = cfg.trainer.enable_progress_bar
    placement = {"accelerator": "cpu", "devices": 1} if exported else {}
    precision = (
        "32-true"
        if exported
        else evaluation_precision(cfg.trainer.precision, loaded, cfg.trainer.accelerator)
    )
    return instantiate(
        cfg.trainer,
        default_root_dir=str(output_dir),
        callbacks=[ProgressLog()],
        logger=logger,
        precision=precision,
        enable_progress_bar=sys.stdout.isatty() if progress is None else progress,
        enable_model_summary=False,
        **placement,
    )


def _resolved_settings(cfg: DictConfig, loaded: LoadedModel, dataset: DictConfig) -> dict:
    """What ``config_resolved.yaml`` records: the evaluate config (its fusion and backbone as
    the model has them: the guards only name a choice, their other keys refer to a training
    config), the dataset scored and the checkpoint's own config."""
    settings = OmegaConf.masked_copy(cfg, [k for k in cfg if k not in ("fusion", "backbone")])
    return {
        "evaluate": {
            **OmegaConf.to_container(settings, resolve=True),
            "fusion": loaded.fusion,
            "backbone": loaded.backbone,
        },
        "dataset": OmegaConf.to_container(dataset, resolve=True),
        "checkpoint_config": loaded.config,
    }


def _scored_source(loaded: LoadedModel, frames: Callable | None) -> dict:
    """Where the scores come from, as the record keeps it: the checkpoint (and the model file
    exported from it, as its sidecar records it), and an aligned prior's fit counts."""
    # A prior read from no file (prior=oracle) is named as the command line names it.
    scored = f"prior={loaded.backbone}" if loaded.path is None else str(loaded.path.resolve())
    source = {"checkpoint": scored}
    if isinstance(loaded.net, ExportedModel):
        source = {"checkpoint": loaded.net.info.checkpoint, "model_file": source["checkpoint"]}
    if isinstance(loaded.net, FallbackCount):
        source["alignment"] = loaded.net.fit_summary()
        ceiling = frames is GroundTruthAsSparse
        source["alignment"]["target"] = "ground_truth" if ceiling else "sparse"
        log.info(
            "alignment: %(fallbacks)d of %(fits)d frame fits fell back, %(reversed)d of them "
            "with returns enough but no fit that keeps the order of depths",
            source["alignment"],
        )
    return source


def evaluate_loaded(
    cfg: DictConfig,
    loaded: LoadedModel,
    output_dir: str | Path,
    served: Sequence[str] = (),
    frames: Callable[[Dataset], Dataset] | None = None,
) -> RunRecord:
    """Score ``loaded`` (a checkpoint's network, or an exported model file's
    :class:`~fusion_depth.export.runtime.ExportedModel`, which runs on the CPU in the
    precision its engine was given, so the Trainer's is fp32); writes ``metrics.json`` and
    ``per_image.csv`` into ``output_dir`` and returns the record written. ``served``: the
    overrides that make it compute otherwise than trained (``prior=none``), added to the
    record's overrides so that ``report`` keeps it apart; ``frames``: wraps each split read
    (:class:`GroundTruthAsSparse`)."""
    exported = isinstance(loaded.net, ExportedModel)
    # Resolved here: once detached from the root config its ${...} references could not be.
    chosen = OmegaConf.to_container(cfg.dataset, resolve=True) if cfg.get("dataset") else None
    block = dataset_config(loaded, chosen)
    reader = _split_reader(block, chosen, loaded, frames)
    dataset = OmegaConf.create(block)
    check_dataset(dataset, loaded.fusion)
    L.seed_everything(cfg.seed, workers=True)
    output_dir = Path(output_dir)
    protocol = EvalProtocol.from_config(cfg.eval, dataset.min_depth, dataset.max_depth)
    module = DepthModule(
        net=loaded.net,
        conditions=list(dataset.get("conditions") or ()),
        channels_last=cfg.model.channels_last and not exported,
        compile=cfg.model.compile and not exported,
        compile_mode=cfg.model.compile_mode,
        protocol=protocol,
    )
    datamodule = DepthDataModule(
        reader=reader,
        batch_size=cfg.data.eval_batch_size,
        num_workers=cfg.data.num_workers,
        test_split=cfg.split,
    )
    logger = instantiate(cfg.logger) if cfg.logger.get("_target_") else False
    trainer = _evaluation_trainer(cfg, loaded, output_dir, logger)
    resolved = _resolved_settings(cfg, loaded, dataset)
    write_text_atomic(output_dir / RESOLVED_CONFIG_FILE, OmegaConf.to_yaml(resolved))
    # Before the work: a malformed record fails first.
    identity = rescored_identity(loaded.run, loaded.config, dataset, engine_identity(loaded.net))
    if served:
        identity = replace(identity, overrides=sorted({*(identity.overrides or []), *served}))
    check_scorable(datamodule, protocol, cfg.trainer, dataset.name, stages=("test",))
    with closing(logger):
        if logger:
            logger.log_hyperparams(resolved)
        if isinstance(loaded.net, FallbackCount):
            loaded.net.reset_fits()
        result = module.run_test(trainer, datamodule, verbose=False)
        source = _scored_source(loaded, frames)
        record = RunRecord.from_result(identity, result, cfg.split, **source, seed=cfg.seed)
        title = (
            f"{cfg.split} metrics of {loaded.path} ({result.overall['num_images']} images, "
            f"{dataset.name}{f', {identity.engine}' if exported else ''})"
        )
        publish_results(output_dir, record, result, trainer.loggers, title)
    return record


def find_checkpoints(folder: Path) -> list[tuple[Path, Path]]:
    """(run folder relative to ``folder``, best checkpoint) of every training run below it.

    A run folder that was moved (or copied from another machine) records its best checkpoint
    where it was written: the file of that name in the run's ``checkpoints/`` is used then."""
    found = []
    for metrics in sorted(folder.rglob(METRICS_FILE)):
        best = read_run_record(metrics).best_checkpoint
        if best is not None and not isinstance(best, str):
            raise CheckpointError(f"{metrics}: best_checkpoint={best!r} is not a path")
        moved = metrics.parent / "checkpoints" / Path(best or "").name  # conf/callbacks' dirpath
        if best and not Path(best).is_file() and moved.is_file():
            best = str(moved)
        if best and Path(best).is_file():
            found.append((metrics.parent.relative_to(folder), Path(best)))
        elif best:
            log.warning("skipping %s: its best checkpoint %s is gone", metrics.parent, best)
    if not found:
        raise FileNotFoundError(
            f"ckpt_path={folder}: no training run with a best checkpoint below it (looked for "
            f"{METRICS_FILE} files naming one)"
        )
    return found


def evaluate(cfg: DictConfig) -> list[dict]:
    """Score ``cfg.ckpt_path`` (one checkpoint, or every run below a folder),
    ``cfg.model_file`` (an exported model file) or ``cfg.released`` (a published checkpoint).
    Returns the contents of each ``metrics.json`` written (:meth:`RunRecord.to_json`)."""
    return [record.to_json() for record in evaluate_records(cfg)]


def evaluate_records(cfg: DictConfig) -> list[RunRecord]:
    """:func:`evaluate`, returning the records written."""
    output_dir = Path(cfg.paths.output_dir)
    if cfg.get("released") is not None:
        return [evaluate_released(cfg, output_dir)]
    if cfg.get("ckpt_path") is None and cfg.get("model_file") is None and _chosen_prior(cfg):
        return [evaluate_alignment(cfg, output_dir)]
    check_source(cfg.get("ckpt_path"), cfg.get("model_file"), prior=True)
    if cfg.get("model_file") is not None:
        return [evaluate_model_file(cfg, Path(cfg.model_file).expanduser(), output_dir)]
    path = Path(cfg.ckpt_path).expanduser()
    if path.is_dir():
        return [
            evaluate_checkpoint(cfg, ckpt, output_dir / run) for run, ckpt in find_checkpoints(path)
        ]
    # A missing file is reported by load_model, naming ckpt_path.
    return [evaluate_checkpoint(cfg, path, output_dir)]
