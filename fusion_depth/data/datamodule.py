"""One LightningDataModule for every dataset: a dataset is a reader config, nothing more."""

from __future__ import annotations

import os
from collections.abc import Callable

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from fusion_depth.data import SPLITS


class IndexedDataset(Dataset):
    """Adds ``"index"`` (the sample's position in its split) to every sample, so evaluation can
    record per-image results that line up across models scored on the same split."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int) -> dict:
        return {**self.dataset[index], "index": index}


def resolve_num_workers(num_workers: int | str) -> int:
    """``data.num_workers``: a count, or ``auto``: with a GPU, one loader process per spare CPU
    core (at most 8) so decoding never starves it; on a CPU-only machine 0, since worker
    processes would take cores from the training itself."""
    if num_workers == "auto":
        cores = os.cpu_count() or 1
        return min(8, max(cores - 1, 1)) if torch.cuda.is_available() else 0
    if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 0:
        raise ValueError(f"data.num_workers={num_workers!r}: expected auto or an integer ≥ 0")
    return num_workers


class DepthDataModule(L.LightningDataModule):
    """Builds split datasets from ``reader(split=...)``, a partial from the dataset config.

    Every reader returns samples ``{"image", "sparse", "depth", "condition"}`` (optionally
    ``"frame_box"``, see :func:`fusion_depth.metrics.crop_mask`), so the model never knows which
    dataset it trains on; the datamodule adds ``"index"``.
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
        self.datasets: dict[str, Dataset] = {}

    def dataset(self, split: str) -> Dataset:
        """The dataset of one split, built on first use."""
        if split not in SPLITS:
            raise ValueError(f"split={split!r}: expected one of {list(SPLITS)}")
        if split not in self.datasets:
            self.datasets[split] = IndexedDataset(self.reader(split=split))
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

    def loader(self, split: str, shuffle: bool, batch_size: int) -> DataLoader:
        """A DataLoader of ``split`` with this module's worker and memory settings (the one
        way loaders are built: the stages below and ``bench``'s data stage)."""
        return DataLoader(
            self.dataset(split),
            batch_size=batch_size,
            shuffle=shuffle,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=self.persistent_workers,
            drop_last=shuffle,
        )

    def train_dataloader(self) -> DataLoader:
        return self.loader("train", True, self.batch_size)

    def val_dataloader(self) -> DataLoader:
        return self.loader("val", False, self.eval_batch_size)

    def test_dataloader(self) -> DataLoader:
        return self.loader(self.test_split, False, self.eval_batch_size)
