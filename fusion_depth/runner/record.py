"""The run record, ``metrics.json``: its fields, its one writer and reader, and the run identity.

A training run (:mod:`fusion_depth.train`) and a re-scored checkpoint
(:mod:`fusion_depth.evaluate`) each end by writing one :class:`RunRecord` into their output
folder; :mod:`fusion_depth.runner.resume`, :mod:`fusion_depth.runner.sweep_summary`,
``evaluate`` (a folder of runs) and :mod:`fusion_depth.report` read it back. This module is the
only one that knows the file's keys: add a field to :class:`RunRecord` (or :class:`RunIdentity`)
and every writer writes it and every reader gets it. (The metrics inside the ``test*`` sections
are keyed by :data:`fusion_depth.metrics.depth.METRIC_KEYS`.)
"""

from __future__ import annotations

import importlib
import json
import math
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from fusion_depth.data.base import PreparedDataset
from fusion_depth.models._registry import DEFAULT_MODEL
from fusion_depth.runner.protocol import (
    EvaluationResult,
    log_to_loggers,
    results_tables,
    write_per_image,
)
from fusion_depth.runner.run_folder import PER_IMAGE_FILE, provenance
from fusion_depth.utils.atomic import write_json_atomic
from fusion_depth.utils.json_file import read_json
from fusion_depth.utils.schema import is_number

METRICS_FILE = "metrics.json"

# Which records write a field (its metadata): every record; a training run's only; a re-scored
# checkpoint's only (``evaluate``); or any record where the value is not None.
_EVERY, _TRAINING, _RESCORED, _IF_SET = "every", "training", "rescored", "if set"


def _written_by(kind: str) -> Any:
    return field(default=None, metadata={"written_by": kind})


@dataclass(frozen=True, kw_only=True)
class _Stored:
    """What a record read from a file keeps so that writing it again loses nothing: the keys
    this version does not know, and which of the known ones the file had."""

    extra: dict[str, Any] = field(default_factory=dict, repr=False)  # unknown keys, as read
    file_keys: frozenset[str] | None = field(default=None, repr=False, compare=False)

    @classmethod
    def _stored_fields(cls) -> list[Any]:
        return [f for f in fields(cls) if "written_by" in f.metadata]

    @classmethod
    def _values(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """Constructor arguments of the record in ``data`` (absent keys: None)."""
        names = {f.name for f in cls._stored_fields()}
        return {
            **{k: v for k, v in data.items() if k in names},
            "extra": {k: v for k, v in data.items() if k not in names},
            "file_keys": frozenset(k for k in data if k in names),
        }

    def _json(self, kind: str) -> dict[str, Any]:
        """Plain data: the keys the file had (for a record read from one), else the fields
        written by every record, by ``kind`` and, where set, the optional ones; then ``extra``."""
        out = {}
        for f in self._stored_fields():
            value = getattr(self, f.name)
            written = f.metadata["written_by"]
            if self.file_keys is not None:
                keep = f.name in self.file_keys
            else:
                keep = written in (_EVERY, kind) or (written == _IF_SET and value is not None)
            if keep:
                out[f.name] = value.to_json() if isinstance(value, RunIdentity) else value
        out.update(self.extra)
        return out


@dataclass(frozen=True, kw_only=True)
class RunIdentity(_Stored):
    """What a run is: the choices ``report`` groups runs by and the overrides that made it.

    Also saved in every checkpoint (:data:`fusion_depth.utils.checkpoint_file.RUN_KEY`), where
    ``resume`` finds the run's overrides and W&B run and ``evaluate`` the training run's
    identity. Built by
    :func:`run_identity` (and :func:`rescored_identity`); values read from a file are as
    recorded, unchecked: readers check the types they rely on.
    """

    dataset: str | None = _written_by(_EVERY)  # dataset.name (re-scored: the dataset scored)
    sensor: str | None = _written_by(_EVERY)  # dataset.sensor (radar, lidar), if it has one
    model: str | None = _written_by(_EVERY)  # model.net.name: densedepth, sparse_to_dense, ...
    backbone: str | None = _written_by(_EVERY)  # backbone.name
    fusion: str | None = _written_by(_EVERY)  # fusion.mode: rgb, concat, add
    loss: str | None = _written_by(_EVERY)  # loss.name if set (l1_only), else loss.pixel
    seed: int | None = _written_by(_EVERY)  # the training run's seed
    overrides: list[str] | None = _written_by(_EVERY)  # those that make the run, sorted, redacted
    wandb_id: str | None = _written_by(_IF_SET)  # training runs: their W&B run (resumes continue)
    trained_on: str | None = _written_by(_IF_SET)  # re-scored runs: the dataset trained on
    # Re-scored runs: what ran the network, ``torch`` (a checkpoint) or an exported model's
    # engine (:func:`fusion_depth.export.runtime.engine_identity`: onnxruntime, torchscript,
    # openvino-fp32|bf16|int8); None (training runs): torch.
    engine: str | None = _written_by(_IF_SET)
    # The format version of the dataset's frames scored (:func:`format_version`): frames of
    # another version (nuScenes' 2 placed points half a pixel off) give other scores. None: a
    # dataset without prepared frames, or a record from before records named it (unknown).
    format_version: int | None = _written_by(_IF_SET)

    def to_json(self) -> dict[str, Any]:
        """The identity as plain data (``wandb_id`` and ``trained_on`` only where set; an
        identity read from a file gives back what was read)."""
        return self._json(_EVERY)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> RunIdentity:
        """The identity in ``data``: absent keys are None, unknown ones kept for writing."""
        return cls(**cls._values(data))


def _reader_class(dataset: Any) -> type | None:
    """The reader class a dataset config block names (``reader._target_``): one already
    loaded, or one of :mod:`fusion_depth.data`'s (imported: the package's own code); None for
    any other, which is never imported (a checkpoint's config names it)."""
    reader = dataset.get("reader") if isinstance(dataset, Mapping) else None
    target = reader.get("_target_") if isinstance(reader, Mapping) else None
    if not isinstance(target, str):
        return None
    module_name, _, name = target.rpartition(".")
    module = sys.modules.get(module_name)
    if module is None and module_name.startswith("fusion_depth.data."):
        try:
            module = importlib.import_module(module_name)
        except ImportError:
            return None
    found = getattr(module, name, None) if module is not None else None
    return found if isinstance(found, type) else None


def format_version(dataset: Any) -> int | None:
    """The format version of the frames that ``dataset`` (a dataset config block) reads: its
    reader's :attr:`~fusion_depth.data.base.PreparedDataset.format_version`, which names the
    prepared cache's folder, so frames of another version are prepared again, never read. The
    cache's own layout version (:data:`~fusion_depth.data.cache.PREPARED_VERSION`) changes how
    values are stored, not the values, and is not part of it. None: a reader without prepared
    frames (the built-in dataset, made in memory), or one that is not loaded and not the
    package's."""
    reader = _reader_class(dataset)
    if reader is None or not issubclass(reader, PreparedDataset):
        return None
    return int(reader.format_version)


def run_identity(
    config: Mapping[str, Any], overrides: Sequence[str] = (), wandb_id: str | None = None
) -> RunIdentity:
    """The identity of the run that ``config`` (a run config: Hydra's, or the plain copy a
    checkpoint holds) configures: its dataset, sensor, model, backbone, fusion mode, pixel loss
    and seed, and its frames' :func:`format_version`; None where the config lacks one.
    ``overrides``: those that made the run (already filtered and redacted by the caller);
    ``wandb_id``: the run's W&B run."""

    def choice(group: str, key: str) -> Any:
        block = config.get(group)
        return block.get(key) if isinstance(block, Mapping) else None

    net = choice("model", "net")
    return RunIdentity(
        dataset=choice("dataset", "name"),
        sensor=choice("dataset", "sensor"),
        # Runs from before models had names trained the paper's network.
        model=net.get("name", DEFAULT_MODEL) if isinstance(net, Mapping) else None,
        backbone=choice("backbone", "name"),
        fusion=choice("fusion", "mode"),
        loss=choice("loss", "name") or choice("loss", "pixel"),
        seed=config.get("seed"),
        overrides=list(overrides),
        wandb_id=wandb_id,
        format_version=format_version(config.get("dataset")),
    )


def training_identity(recorded: Mapping[str, Any] | None, config: Mapping[str, Any]) -> RunIdentity:
    """The training run's identity as ``recorded`` in a checkpoint (or an exported model's
    sidecar), rebuilt from its run ``config`` by :func:`run_identity` where none is, or not as
    train writes it."""
    identity = RunIdentity.from_json(recorded or {})
    if not isinstance(identity.dataset, str):
        identity = run_identity(config)
    return identity


def rescored_identity(
    recorded: Mapping[str, Any] | None,
    config: Mapping[str, Any],
    dataset: Mapping[str, Any],
    engine: str = "torch",
) -> RunIdentity:
    """The identity of a checkpoint re-scored on ``dataset`` (a dataset config block): the
    training run's identity (:func:`training_identity`), with the dataset, sensor and
    :func:`format_version` scored now, ``trained_on`` the dataset it was trained on and
    ``engine`` what ran the network (``torch`` for a checkpoint, an exported model's engine
    identity)."""
    identity = training_identity(recorded, config)
    version = format_version(dataset)
    # Written: the keys it had, and those set here (even where None; the version where known).
    keys = frozenset(identity.to_json()) | {"dataset", "sensor", "trained_on", "engine"}
    return replace(
        identity,
        trained_on=identity.dataset,
        dataset=dataset.get("name"),
        sensor=dataset.get("sensor"),
        engine=engine,
        format_version=version,
        file_keys=keys | ({"format_version"} if version is not None else set()),
    )


@dataclass(frozen=True, kw_only=True)
class RunRecord(_Stored):
    """One run's ``metrics.json``: its fields in the order they are written.

    Training runs write the common fields and the training ones; a re-scored checkpoint (one
    with ``checkpoint`` set) the common fields, ``checkpoint`` and ``seed``. Build a finished
    run's record with :meth:`from_result`; a record read from a file
    (:func:`read_run_record`) may lack any field (None): older versions wrote fewer. Written
    again, a record read from a file gives back what was read.
    The metric dicts (``test`` and each group of the ``test_by_*`` sections) hold every key of
    :data:`~fusion_depth.metrics.depth.METRIC_KEYS` plus ``num_images`` and ``num_pixels``.
    """

    status: str | None = _written_by(_EVERY)  # "ok" (a failed run writes failure.json instead)
    run: RunIdentity | None = _written_by(_EVERY)  # what the run is
    split: str | None = _written_by(_EVERY)  # the split scored: test (training), any (evaluate)
    protocol: dict[str, Any] | None = _written_by(_EVERY)  # EvalProtocol.as_dict()
    test: dict[str, float] | None = _written_by(_EVERY)  # the headline metrics (largest cap)
    test_by_condition: dict[str, dict[str, float]] | None = _written_by(_EVERY)  # per condition
    test_by_distance: dict[str, dict[str, float]] | None = _written_by(_EVERY)  # "0-10" (m), ...
    test_by_cap: dict[str, dict[str, float]] | None = _written_by(_EVERY)  # per depth cap "80"
    latency: dict[str, Any] | None = _written_by(_EVERY)  # protocol.latency_summary (seconds)
    per_image_file: str | None = _written_by(_EVERY)  # relative to metrics.json's folder
    best_checkpoint: str | None = _written_by(_TRAINING)  # the checkpoint tested; None: last
    best_val_rmse: float | None = _written_by(_TRAINING)  # its validation RMSE (m)
    epochs: int | None = _written_by(_TRAINING)  # epochs trained
    resumed_from: str | None = _written_by(_TRAINING)  # the last.ckpt the run continued from
    global_step: int | None = _written_by(_TRAINING)  # optimizer steps
    validation: list[dict[str, float | int]] | None = _written_by(_TRAINING)  # every epoch's
    wall_time_s: float | None = _written_by(_TRAINING)  # fit + test, seconds
    checkpoint: str | None = _written_by(_RESCORED)  # the checkpoint scored (absolute path)
    # An exported model scored (evaluate model_file=; absolute path); ``checkpoint`` is then
    # the one it was exported from, as its sidecar records it (None for a bare network).
    model_file: str | None = _written_by(_IF_SET)
    seed: int | None = _written_by(_RESCORED)  # evaluate's seed
    # A prior's alignment (global alignment, prior_correction): its settings, frame fits and
    # fallbacks (fits of frames with fewer than 2 returns), fusion_depth.models.alignment.
    alignment: dict[str, Any] | None = _written_by(_IF_SET)
    versions: dict[str, Any] | None = _written_by(_EVERY)  # runs.provenance()
    path: Path | None = field(default=None, compare=False)  # where it was read from; not written

    @classmethod
    def from_result(
        cls, identity: RunIdentity, result: EvaluationResult, split: str, **outcome: Any
    ) -> RunRecord:
        """The record of a finished run scored on ``split`` with ``result`` (the test stage's,
        :meth:`fusion_depth.runner.module.DepthModule.run_test`); ``outcome``: the training
        fields (train) or ``checkpoint`` and ``seed`` (evaluate). Adds the package versions."""
        return cls(
            status="ok",
            run=identity,
            split=split,
            protocol=result.protocol.as_dict(),
            test=result.overall,
            test_by_condition=result.by_condition,
            test_by_distance=result.by_distance,
            test_by_cap=result.by_cap,
            latency=dict(result.latency) if result.latency else None,
            per_image_file=PER_IMAGE_FILE,
            **outcome,
            versions=provenance(),
        )

    @property
    def rescored(self) -> bool:
        """Whether this is ``evaluate``'s record of a re-scored checkpoint (or exported model
        file), not a training run's."""
        return self.checkpoint is not None or self.model_file is not None

    @property
    def finished(self) -> bool:
        """A finished run's record: status ok, test metrics, and for a training run at least
        one optimizer step trained (a run that trained nothing is never done); ``evaluate``'s
        records (:attr:`rescored`) are finished once written."""
        steps = self.global_step
        trained = isinstance(steps, int) and not isinstance(steps, bool) and steps > 0
        return self.status == "ok" and (trained or self.rescored) and isinstance(self.test, dict)

    def breakdown(self, by: str) -> dict[str, dict[str, float]] | None:
        """The ``test_by_<by>`` section (``by``: a key of :data:`BREAKDOWNS`); None if absent."""
        return getattr(self, BREAKDOWNS[by])

    def to_json(self) -> dict[str, Any]:
        """The record as written to ``metrics.json`` (plain data, in the file's key order)."""
        return self._json(_RESCORED if self.rescored else _TRAINING)

    @classmethod
    def from_json(cls, data: Any, path: str | os.PathLike | None = None) -> RunRecord:
        """The record in ``data`` (a parsed ``metrics.json``, read from ``path``): absent keys
        are None, unknown ones kept for writing, values as recorded.

        Raises:
            ValueError: ``data`` (or its ``run``) is not a mapping, naming ``path``.
        """
        where = path if path is not None else "metrics"
        if not isinstance(data, Mapping):
            raise ValueError(
                f"{where}: not a fusion-depth metrics file (a JSON {type(data).__name__}, not "
                "an object)"
            )
        values = cls._values(data)
        run = values.get("run")
        if run is not None:
            if not isinstance(run, Mapping):
                raise ValueError(f"{where}: 'run' is not a mapping")
            values["run"] = RunIdentity.from_json(run)
        return cls(**values, path=None if path is None else Path(path))


# --by choice of ``report`` → the RunRecord field holding one metrics dict per column.
BREAKDOWNS: dict[str, str] = {
    "condition": "test_by_condition",
    "distance": "test_by_distance",
    "cap": "test_by_cap",
}


def write_run_record(output_dir: str | os.PathLike, record: RunRecord) -> Path:
    """Write ``record`` to ``output_dir/metrics.json`` atomically; returns the file's path."""
    path = Path(output_dir) / METRICS_FILE
    write_json_atomic(path, record.to_json())
    return path


def read_run_record(path: str | os.PathLike) -> RunRecord:
    """The record in ``path`` (a ``metrics.json``).

    Raises:
        OSError: the file cannot be read.
        ValueError: it is not JSON, or not a metrics file; the message names the file.
    """
    path = Path(path)
    return RunRecord.from_json(read_json(path, "a metrics file"), path)


def read_finished(output_dir: str | os.PathLike) -> RunRecord | None:
    """The record in ``output_dir``'s ``metrics.json`` if it is a finished training run's
    (:attr:`RunRecord.finished`), else None (also when the file is missing or unreadable)."""
    try:
        record = read_run_record(Path(output_dir) / METRICS_FILE)
    except (OSError, ValueError):
        return None
    return record if record.finished else None


def _is_score(value: Any) -> bool:
    return is_number(value) and math.isfinite(value)


def check_scores(record: RunRecord) -> None:
    """Refuse a record whose scores a table would print wrong: ``test`` and every group of
    the ``test_by_*`` sections must map names to finite numbers (the evaluator leaves out a
    group without a scored image, so a NaN never belongs there).

    Raises:
        ValueError: naming the file, the key and what was found.
    """
    sections: list[tuple[str, Any]] = [("test", record.test)]
    for by, name in BREAKDOWNS.items():
        section = record.breakdown(by)
        if section is None:
            continue
        if not isinstance(section, dict):
            raise ValueError(
                f"{record.path}: {name}: expected an object of groups, got {type(section).__name__}"
            )
        sections += [(f"{name}.{group}", values) for group, values in section.items()]
    for key, values in sections:
        if not isinstance(values, dict):
            raise ValueError(
                f"{record.path}: {key}: expected an object of metric values, got "
                f"{type(values).__name__}"
            )
        for metric, value in values.items():
            if not _is_score(value):
                raise ValueError(
                    f"{record.path}: {key}.{metric}={json.dumps(value)[:40]}: expected a finite "
                    "number"
                )


def load_runs(root: str | os.PathLike) -> list[RunRecord]:
    """Every ``metrics.json`` below ``root``, sorted by path, each with its ``path`` set.

    Raises:
        FileNotFoundError: ``root`` is not a directory.
        ValueError: a file is not a metrics file (:func:`read_run_record`), lacks the
            ``run`` and ``test`` sections, or holds a score that is not a finite number
            (:func:`check_scores`).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such directory")
    runs = []
    for path in sorted(root.rglob(METRICS_FILE)):
        record = read_run_record(path)
        if record.run is None or record.test is None:
            raise ValueError(f"{path}: expected a fusion-depth metrics file with 'run' and 'test'")
        check_scores(record)
        runs.append(record)
    return runs


def publish_results(
    output_dir: str | os.PathLike,
    record: RunRecord,
    result: EvaluationResult,
    loggers: Sequence[Any],
    title: str,
) -> Path:
    """Send ``result``'s breakdowns to W&B, write ``per_image.csv`` then ``metrics.json`` (last,
    so its presence means the run is complete), and print ``title`` with the tables. Returns
    the path of ``metrics.json``."""
    log_to_loggers(loggers, result)
    output_dir = Path(output_dir)
    write_per_image(output_dir / PER_IMAGE_FILE, result.per_image)
    path = write_run_record(output_dir, record)
    print(f"\n{title}:\n{results_tables(result)}\nWritten to {path}", flush=True)
    return path
