"""One LightningDataModule for every dataset: a dataset is a reader config, nothing more."""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from fusion_depth.data import SPLITS
from fusion_depth.data.encoding import decode_sample
from fusion_depth.errors import ConfigError
from fusion_depth.runner.prior_cache import CachedPriorFrames, PriorCache
from fusion_depth.utils.schema import NON_NEGATIVE_INT, POSITIVE_INT, Rule, Schema, is_int, one_of

log = logging.getLogger(__name__)


def epoch_seed(seed: int, epoch: int) -> int:
    """A seed for ``epoch`` of a run seeded with ``seed``, independent of anything drawn before."""
    return int(np.random.SeedSequence([seed, epoch]).generate_state(1)[0])


class EpochSampler(Sampler[int]):
    """The training order: each epoch a permutation drawn from (seed, epoch) alone.

    So a run restarted at any epoch sees the order an uninterrupted run would; ``skip`` (set by
    :class:`ResumableLoader` after a mid-epoch restore) drops the samples already trained on.
    Lightning calls ``set_epoch`` before every epoch.
    """

    def __init__(self, size: int, seed: int) -> None:
        self.size = size
        self.seed = seed
        self.epoch = 0
        self.skip = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.size

    def __iter__(self) -> Iterator[int]:
        generator = torch.Generator().manual_seed(epoch_seed(self.seed, self.epoch))
        order = torch.randperm(self.size, generator=generator).tolist()
        skip, self.skip = self.skip, 0
        yield from order[skip:]


class ResumableLoader(DataLoader):
    """A training DataLoader that Lightning checkpoints with the run (its stateful-loader
    protocol, ``state_dict``/``load_state_dict``): the epoch and how many of its batches were
    handed out. Restored mid-epoch, its next pass over that epoch starts at the following
    batch, so a resumed run trains on exactly the batches an uninterrupted one would.

    Lightning does not prefetch from a loader of known length, so the count handed out is the
    count trained when a checkpoint is written after a batch.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.base_seed = self.generator.initial_seed() if self.generator is not None else 0
        self.batches_handed_out = 0
        self._resume_at: tuple[int, int] | None = None  # (epoch, batches done) after a restore

    def state_dict(self) -> dict[str, int]:
        epoch = getattr(self.sampler, "epoch", 0)
        return {"epoch": epoch, "batches": self.batches_handed_out}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self._resume_at = (int(state["epoch"]), int(state["batches"]))

    def __iter__(self) -> Iterator[Any]:
        return self._batches()

    def _batches(self) -> Iterator[Any]:
        # A generator: runs at the first next(), after Lightning's set_epoch for this epoch.
        sampler = self.sampler
        epoch = getattr(sampler, "epoch", 0)
        done = 0
        if self._resume_at is not None:
            resume_epoch, resume_batches = self._resume_at
            self._resume_at = None
            if resume_epoch == epoch and resume_batches:
                if isinstance(sampler, EpochSampler):
                    sampler.skip = resume_batches * (self.batch_size or 1)
                    done = resume_batches
                else:  # e.g. Lightning's distributed sampler wrapper under DDP
                    log.warning(
                        "resuming mid-epoch %d: this sampler (%s) cannot skip the %d batches "
                        "already trained, so the epoch's first batches are seen again",
                        epoch,
                        type(sampler).__name__,
                        resume_batches,
                    )
        if self.generator is not None:  # worker seeds per epoch, not per restart
            self.generator.manual_seed(epoch_seed(self.base_seed, epoch))
        self.batches_handed_out = done
        for batch in super().__iter__():
            self.batches_handed_out += 1
            yield batch


class IndexedDataset(Dataset):
    """What the loaders read: each sample of ``dataset`` in the form that crosses the process
    boundary, the :class:`~fusion_depth.data.EncodedSample` from ``dataset.encoded_sample(i)``
    where the reader has that method (else ``dataset[i]`` as it is), plus ``"index"`` (the
    sample's position in its split), so evaluation can record per-image results that line up
    across models scored on the same split. The float form comes from
    :func:`~fusion_depth.data.encoding.decode_sample`, on the device
    (``DepthModule.on_after_batch_transfer``)."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int) -> dict:
        read = getattr(self.dataset, "encoded_sample", None)
        return {**(read(index) if read is not None else self.dataset[index]), "index": index}


def resolve_num_workers(num_workers: int | str) -> int:
    """``data.num_workers``: a count, or ``auto``: with a GPU, one loader process per spare CPU
    core (at most 8) so decoding never starves it; on a CPU-only machine 0, since worker
    processes would take cores from the training itself."""
    if num_workers == "auto":
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        cores = cores or 1  # the cores this process may use: a SLURM job's, not the node's
        return min(8, max(cores - 1, 1)) if torch.cuda.is_available() else 0
    if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 0:
        raise ValueError(f"data.num_workers={num_workers!r}: expected auto or an integer ≥ 0")
    return num_workers


class DepthDataModule(L.LightningDataModule):
    """Builds split datasets from ``reader(split=...)``, a partial from the dataset config.

    Every reader returns samples ``{"image", "sparse", "depth", "condition"}`` (optionally
    ``"frame_box"``, see :func:`fusion_depth.metrics.depth.crop_mask`, and, from a radar dataset,
    ``"radar_points"`` (P, K), which batch to (B, P, K): P is fixed per dataset config), so the
    model never knows which dataset it trains on; the datamodule adds ``"index"``. Every sample
    of a split has the same keys, as the default collate needs. Loaders carry the encoded form
    where a reader has one (uint8 image, uint16 depth maps: see :class:`IndexedDataset`), which
    the module decodes on the device.
    """

    def __init__(
        self,
        reader: Callable[..., Dataset],
        batch_size: int = 2,
        eval_batch_size: int | None = None,
        num_workers: int | str = "auto",
        pin_memory: bool | None = None,
        persistent_workers: bool | None = None,
        test_split: str = "test",
        seed: int = 0,
    ) -> None:
        super().__init__()
        if batch_size < 1:
            raise ValueError(f"data.batch_size={batch_size}: expected an integer ≥ 1")
        self.reader = reader
        self.batch_size = batch_size
        self.eval_batch_size = eval_batch_size or batch_size
        self.num_workers = resolve_num_workers(num_workers)
        # Pinned memory and persistent workers only pay off when a GPU consumes the batches.
        self.pin_memory = torch.cuda.is_available() if pin_memory is None else pin_memory
        self.persistent_workers = self.num_workers > 0 and (
            persistent_workers is None or persistent_workers
        )
        if test_split not in SPLITS:
            raise ValueError(f"split={test_split!r}: expected one of {list(SPLITS)}")
        self.test_split = test_split  # what the test stage scores (evaluate's split=)
        self.seed = seed  # the training order's (see EpochSampler)
        self.datasets: dict[str, Dataset] = {}
        # Set by train: the frames' cached prior, added to the training and validation batches
        # (the test stage runs the prior itself, as the deployed model does).
        self.prior_cache: PriorCache | None = None
        # Set by train for a network whose loss reads the measured ground truth beside the
        # filled one (``wants_measured_depth``): the training split serves it as depth_measured.
        self.measured_depth = False

    def dataset(self, split: str) -> Dataset:
        """The dataset of one split, built on first use."""
        if split not in SPLITS:
            raise ValueError(f"split={split!r}: expected one of {list(SPLITS)}")
        if split not in self.datasets:
            dataset = self.reader(split=split)
            if split == "train" and self.measured_depth and hasattr(dataset, "serve_measured"):
                dataset.serve_measured = True
            self.datasets[split] = IndexedDataset(dataset)
        return self.datasets[split]

    def setup(self, stage: str | None = None) -> None:
        needed = {
            "fit": ("train", "val"),
            "validate": ("val",),
            "test": (self.test_split,),
            "predict": (self.test_split,),
        }.get(stage or "", SPLITS)
        for split in needed:
            self.dataset(split)

    def loader(self, split: str, shuffle: bool, batch_size: int, prior: bool = False) -> DataLoader:
        """A DataLoader of ``split`` with this module's worker and memory settings (the one
        way loaders are built: the stages below and ``bench``'s data stage). Shuffled loaders
        are resumable (see :class:`ResumableLoader`); every loader draws its worker seeds from
        its own generator, so iterating one never moves the global RNG that augmentation uses.
        ``prior``: each sample carries its cached prior too, where :attr:`prior_cache` is set."""
        dataset = self.dataset(split)
        if prior and self.prior_cache is not None:
            dataset = CachedPriorFrames(dataset, self.prior_cache)
        common = {
            "batch_size": batch_size,
            "num_workers": self.num_workers,
            "pin_memory": self.pin_memory,
            "persistent_workers": self.persistent_workers,
            "generator": torch.Generator().manual_seed(self.seed),
        }
        if shuffle:
            sampler = EpochSampler(len(dataset), self.seed)
            return ResumableLoader(dataset, sampler=sampler, drop_last=True, **common)
        return DataLoader(dataset, shuffle=False, **common)

    def train_dataloader(self) -> DataLoader:
        return self.loader("train", True, self.batch_size, prior=True)

    def val_dataloader(self) -> DataLoader:
        return self.loader("val", False, self.eval_batch_size, prior=True)

    def test_dataloader(self) -> DataLoader:
        return self.loader(self.test_split, False, self.eval_batch_size)


def _batches_left(limit: Any, batches: int) -> int:
    """The batches Lightning runs of ``batches`` under ``trainer.limit_*_batches`` (None: all;
    an int: at most that many; a float: that fraction, rounded down)."""
    if limit is None:
        return batches
    if isinstance(limit, float) and limit <= 1.0:
        return int(batches * limit)
    return min(int(limit), batches)


def check_batches(
    datamodule: DepthDataModule, trainer: Mapping[str, Any], dataset: str, world_size: int = 1
) -> None:
    """Refuse, before any training, a run in which a stage would see no batch: a split with no
    frames, a training split smaller than one batch (the last partial batch is dropped), or a
    ``trainer.limit_{train,val,test}_batches`` that leaves none. Each process of a
    ``world_size``-process run gets its share of the training and validation frames; the test
    stage runs on one process.

    Raises:
        ConfigError: one line naming the split, its size and the batch size (or the limit).
    """
    # trainer.max_epochs=0 is refused with the other config values (fusion_depth.config.validation).
    if trainer.get("max_steps") == 0:
        raise ConfigError("trainer.max_steps=0: leaves nothing to train; expected at least 1")
    stages = (
        ("train", "train", datamodule.batch_size, "data.batch_size"),
        ("val", "val", datamodule.eval_batch_size, "data.eval_batch_size"),
        ("test", datamodule.test_split, datamodule.eval_batch_size, "data.eval_batch_size"),
    )
    for stage, split, batch_size, batch_key in stages:
        frames = len(datamodule.dataset(split))
        if frames == 0:
            raise ConfigError(f"dataset={dataset}: the {split} split has no frames")
        share = frames if stage == "test" else math.ceil(frames / world_size)
        if stage == "train":
            batches = share // batch_size  # drop_last: a partial batch is never trained
            if batches == 0:
                per = f" per process of {world_size}" if world_size > 1 else ""
                raise ConfigError(
                    f"{batch_key}={batch_size}: the train split of dataset={dataset} has "
                    f"{share} frame{'s' if share != 1 else ''}{per}, fewer than one batch (the "
                    "last partial batch is dropped); lower the batch size or add frames"
                )
        else:
            batches = math.ceil(share / batch_size)
        limit = trainer.get(f"limit_{stage}_batches")
        if _batches_left(limit, batches) == 0:
            raise ConfigError(
                f"trainer.limit_{stage}_batches={limit}: leaves no batch of the {split} split "
                f"of dataset={dataset} ({frames} frames, {batch_key}={batch_size}, "
                f"{batches} batch{'es' if batches != 1 else ''})"
            )


def check_scorable(
    datamodule: DepthDataModule,
    protocol: Any,
    trainer: Mapping[str, Any],
    dataset: str,
    stages: tuple[str, ...] = ("val", "test"),
) -> None:
    """Refuse, before any training, a validation or test split of which no frame that the stage
    sees has a pixel the metrics can score: ground truth in ``(protocol.min_depth, largest
    cap)`` inside ``protocol.crop`` (:func:`fusion_depth.metrics.depth.scored_mask`). Such a split
    would otherwise end the first validation with "DepthMetrics has not scored any image", e.g.
    a KITTI frame whose lidar rows lie outside the bottom-centre crop of a small
    ``dataset.height``. Frames are read in the stage's order until one can be scored, so a good
    split costs one frame.

    Args:
        protocol: an :class:`~fusion_depth.runner.protocol.EvalProtocol` (``min_depth``,
            ``max_depth`` caps, ``crop``).
        trainer: the trainer config (its ``limit_{stage}_batches``).
        dataset: the dataset's name, for the message.
        stages: ``val`` and/or ``test`` (the test stage reads ``datamodule.test_split``).

    Raises:
        ConfigError: naming the split, the frames checked, the sample size and the crop, and
            what to change.
    """
    from fusion_depth.metrics.depth import scored_mask

    cap = max(protocol.max_depth)
    for stage in stages:
        split = "val" if stage == "val" else datamodule.test_split
        data = datamodule.dataset(split)
        batch = datamodule.eval_batch_size
        seen = _batches_left(trainer.get(f"limit_{stage}_batches"), math.ceil(len(data) / batch))
        count = min(len(data), seen * batch)
        shape = None
        for index in range(count):
            sample = decode_sample(data[index])
            depth = torch.as_tensor(sample["depth"])[None]
            shape = tuple(depth.shape[-2:])
            box = sample.get("frame_box")
            box = None if box is None else torch.as_tensor(box).reshape(1, 4)
            if scored_mask(depth, protocol.min_depth, cap, protocol.crop, box).any():
                break
        else:
            size = f"{shape[0]}×{shape[1]}" if shape else "?"
            crop = f" inside eval.crop={protocol.crop}" if protocol.crop != "none" else ""
            raise ConfigError(
                f"dataset={dataset}: the {split} split cannot be scored: none of the {count} "
                f"frames its {stage} stage reads (indices 0-{count - 1}) has a ground-truth "
                f"depth in ({protocol.min_depth:g}, {cap:g}) m{crop} within its {size} sample "
                "(dataset.height × dataset.width; readers that cut a larger frame keep its "
                "bottom centre). Raise dataset.height/dataset.width, widen eval.min_depth/"
                "eval.max_depth or eval.crop, or check that split's ground truth"
            )


# The ``data`` block's values (:class:`DepthDataModule`'s arguments) and the run's seed, which
# it takes too (fusion_depth.utils.schema).
CONFIG_SCHEMA: Schema = {
    "seed": Rule(is_int, "an integer"),
    "data.batch_size": POSITIVE_INT,
    "data.eval_batch_size": POSITIVE_INT.or_null("data.batch_size"),
    "data.num_workers": Rule(
        lambda v: v == "auto" or NON_NEGATIVE_INT.ok(v), "auto or an integer ≥ 0"
    ),
    "data.pin_memory": one_of(None, True, False),
    "data.persistent_workers": one_of(None, True, False),
    "data.test_split": one_of(*SPLITS),
}
