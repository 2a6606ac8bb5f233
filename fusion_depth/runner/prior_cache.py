"""Cached priors: a frozen prior's depth computed once per frame and read back by the loaders,
so the networks on top of it train at their own cost (``prior.cache: true``, the default;
``prior.cache=false`` runs the prior on every batch instead).

Each frame's prior is stored under
``<cache root>/priors/<prior key>/<digest[:2]>/<digest>.npy`` as float16 (H, W) at the frame's
size: what the prior module returns for the frame's image (before augmentation),

* for a **relative** prior (``kind: relative``), mapped to [0, 1] per frame
  (:func:`~fusion_depth.models.depth_prior.normalized_prior`), the form the networks read it
  in (an affine-invariant prior carries its shape in the frame, not its range);
* for a **metric** prior (``kind: metric``), as it is: depth in metres, in [0, max_depth].
  float16 holds 11 significant bits: a step of 1/16 m from 64 m to 128 m (3 cm at most off,
  rounded), 1/32 m from 32 m; a relative error of at most 2^-11 = 0.05 % at any depth, well
  below what any depth metric resolves, so float32 would only double the cache;

and:

* the **prior key** is a digest of the prior's name, its weights' content (SHA-256 of the file,
  or of every file of a folder, :func:`weights_digest`), its ``input_size``, its kind and range
  (``kind``, ``max_depth``, resolved by
  :func:`~fusion_depth.models.depth_prior.resolve_prior_kind`: a relative and a metric cache of
  the same ``.pth`` never mix) and
  :data:`PRIOR_CACHE_VERSION`: other weights, even at the same path, are another folder;
* the **frame digest** is a digest of the frame's image as the loaders serve it (its dtype,
  shape and bytes, :func:`frame_digest`): a frame whose image changed (a dataset prepared again
  with other settings, another dataset) finds no stale prior; identical images share one.

So the cache is keyed by the weights, the input size and the data itself, and needs no index to
go stale. Files are written under a temporary name and renamed (two processes filling one folder
write the same bytes), and the temporaries of killed writers are removed when the cache is
opened (:meth:`PriorCache.sweep`); ``meta.json`` records what made the folder. float16 keeps
three significant digits of each value in [0, 1]; a network trained on the cache sees the prior
of the un-jittered image (the colour jitter reaches the image only), where
``prior.cache=false`` runs it on the jittered one.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from fusion_depth.data import cache_dir
from fusion_depth.data.cache import check_settings_file
from fusion_depth.data.depth_io import DataFileError, read_npy, write_npy
from fusion_depth.data.encoding import decode_sample
from fusion_depth.errors import ArgumentError
from fusion_depth.models.depth_prior import (
    METRIC,
    RELATIVE,
    normalized_prior,
    resolve_prior_kind,
    weights_digest,
)
from fusion_depth.utils.atomic import remove_orphaned_temporaries

log = logging.getLogger(__name__)

# Bump when what a cached prior holds changes (2: normalised per frame; 3: Depth Anything resized
# bicubically at the authors' sizes, a metric prior's metres).
PRIOR_CACHE_VERSION = 3
PRIOR_DTYPE = np.float16


def frame_digest(image: torch.Tensor) -> str:
    """A digest of one frame's image as the loaders serve it ((3, H, W), encoded uint8 or
    float): its dtype, shape and bytes."""
    array = image.detach().cpu().contiguous().numpy()
    digest = hashlib.blake2b(f"{array.dtype}{array.shape}".encode(), digest_size=16)
    digest.update(memoryview(array).cast("B"))
    return digest.hexdigest()


class PriorCache:
    """One prior's cached frames (see the module docstring).

    Args:
        spec: the ``prior`` node (``name``, ``weights``, ``input_size``, ``kind``,
            ``max_depth``; the last two null or absent: from the weights).
        root: the cache root (default: :func:`~fusion_depth.data.cache_dir`).

    Attributes:
        kind: ``relative`` (frames stored normalised to [0, 1]) or ``metric`` (stored in
            metres); max_depth: a metric prior's range, metres, else None.

    Raises:
        ArgumentError: the weights do not exist, or ``kind`` or ``max_depth`` disagree with
            them (:func:`~fusion_depth.models.depth_prior.resolve_prior_kind`).
        DataFileError: the folder's ``meta.json`` records other settings.
    """

    def __init__(self, spec: Mapping[str, Any], root: str | Path | None = None) -> None:
        self.kind, self.max_depth = resolve_prior_kind(
            spec["name"], spec["weights"], spec.get("kind"), spec.get("max_depth")
        )
        settings = {
            "version": PRIOR_CACHE_VERSION,
            "name": spec["name"],
            "weights_sha256": weights_digest(spec["weights"]),
            "input_size": spec.get("input_size"),
            "kind": self.kind,
            "max_depth": self.max_depth,
        }
        key = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
        self.folder = Path(root if root is not None else cache_dir()) / "priors" / key
        self.folder.mkdir(parents=True, exist_ok=True)
        check_settings_file(self.folder / "meta.json", settings, self.folder)
        self.sweep()

    def sweep(self) -> list[Path]:
        """Remove the temporary files that killed writers left in the folder
        (``<digest[:2]>/.<digest>.npy.p<pid>h<host>.<random>.npy``: a kill while it filled),
        by the platform's one rule (:func:`~fusion_depth.utils.atomic.remove_orphaned_temporaries`:
        a process of this machine that is gone, or another machine's older than 10 min). One
        that a live process is writing stays. Called when the cache is opened.

        Returns:
            The files removed.
        """
        removed = remove_orphaned_temporaries(self.folder, recursive=True)
        if removed:
            log.info("prior: removed %d temporary files of killed writers", len(removed))
        return removed

    def path(self, digest: str) -> Path:
        """Where the prior of the frame with ``digest`` is stored."""
        return self.folder / digest[:2] / f"{digest}.npy"

    def read(self, image: torch.Tensor) -> torch.Tensor:
        """The cached prior of the frame whose image is ``image`` (3, H, W): (1, H, W) float16,
        a relative prior's normalised to [0, 1] per frame, a metric prior's (:attr:`kind`
        ``metric``) depth in metres, in [0, :attr:`max_depth`], unnormalised.

        Raises:
            DataFileError: none is cached (the cache was filled for other frames, or deleted
                since), or the file is damaged.
        """
        path = self.path(frame_digest(image))
        if not path.is_file():
            raise DataFileError(
                path,
                "no cached prior for this frame; run python -m fusion_depth.prepare with the "
                "same prior= and dataset settings, or set prior.cache=false",
            )
        shape = tuple(image.shape[-2:])
        array = read_npy(path, PRIOR_DTYPE, shape, "cached prior", f"delete {path}")
        return torch.from_numpy(np.array(array))[None]

    @torch.no_grad()
    def fill(
        self,
        prior: nn.Module,
        frames: Dataset,
        what: str,
        batch_size: int = 4,
        device: torch.device | str = "cpu",
    ) -> int:
        """Compute and store the prior of every frame of ``frames`` not cached yet, in fp32:
        a relative prior's normalised to [0, 1] per frame, a metric one's in metres.

        Args:
            prior: the frozen prior ((B, 1, H, W) from (B, 3, H, W)): its ``kind`` (relative
                where it has none) and ``max_depth`` must be the cache's.
            frames: samples with ``image`` (encoded or float, as the loaders serve them).
            what: the frames' name for the log (``train split``).
            batch_size: frames run through the prior at once.
            device: where the prior runs.

        Returns:
            The number of frames computed (0 when all were cached).

        Raises:
            ArgumentError: ``prior`` is of another kind or range than the cache (one line naming
                both): its frames would be stored in another form than :meth:`read` serves.
        """
        given = (getattr(prior, "kind", RELATIVE), getattr(prior, "max_depth", None))
        if given != (self.kind, self.max_depth):
            raise ArgumentError(
                f"{{kind}}={self.kind}: the prior cache {self.folder} holds kind={self.kind} "
                f"max_depth={self.max_depth}, but the prior given to fill it is kind={given[0]} "
                f"max_depth={given[1]}; expected both built from the same prior settings",
                "kind",
                owner="fusion_depth.models.depth_prior",
            )
        started = time.perf_counter()
        prior = prior.to(device).eval()
        pending: dict[str, torch.Tensor] = {}  # a batch of frames not cached yet, by digest
        computed = 0
        for index in range(len(frames)):
            image = frames[index]["image"]
            digest = frame_digest(image)
            if digest not in pending and not self.path(digest).is_file():
                pending[digest] = image
            if len(pending) == batch_size or (pending and index == len(frames) - 1):
                self._store(prior, pending, device)
                computed += len(pending)
                pending = {}
        if computed:
            took = time.perf_counter() - started
            log.info(
                "prior: %d of %d frames of the %s computed in %.1f s (%.1f frames/s) into %s",
                computed,
                len(frames),
                what,
                took,
                computed / max(took, 1e-9),
                self.folder,
            )
        return computed

    def _store(
        self, prior: nn.Module, images: Mapping[str, torch.Tensor], device: torch.device | str
    ) -> None:
        """Run ``prior`` on ``images`` (by frame digest) and write each frame's file."""
        batch = decode_sample({"image": torch.stack(list(images.values()))})["image"]
        out = prior(batch.to(device).float()).float()
        # A relative prior is stored normalised: an affine-invariant prior may span any range
        # (an SSI-trained network's reaches 1e5 and more, beyond float16), and what the networks
        # read is its shape in the frame (normalized_prior), which [0, 1] keeps to 3 digits. A
        # metric one in metres, as it is: at most max_depth, within float16's range.
        frames = (out if self.kind == METRIC else normalized_prior(out)).cpu().numpy()
        for digest, frame in zip(images, frames, strict=True):
            self.path(digest).parent.mkdir(exist_ok=True)
            write_npy(self.path(digest), frame[0].astype(PRIOR_DTYPE))


class CachedPriorFrames(Dataset):
    """``frames`` (samples with ``image``) with each frame's cached prior added as ``prior``
    ((1, H, W) float16, :meth:`PriorCache.read`: normalised to [0, 1] for a relative prior,
    metres for a metric one)."""

    def __init__(self, frames: Dataset, cache: PriorCache) -> None:
        self.frames, self.cache = frames, cache

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> dict:
        sample = self.frames[index]
        return {**sample, "prior": self.cache.read(sample["image"])}


def fill_prior_caches(
    cache: PriorCache,
    prior: nn.Module,
    datasets: Iterable[tuple[str, Dataset]],
    device: torch.device | str = "cpu",
) -> int:
    """:meth:`PriorCache.fill` for each (split, frames) of ``datasets``; the frames computed."""
    return sum(
        cache.fill(prior, frames, f"{split} split", device=device) for split, frames in datasets
    )


CACHED_SPLITS = ("train", "val")  # what the cache serves; the test stage runs the prior itself


def uses_prior_cache(spec: Mapping[str, Any] | None) -> bool:
    """Whether a ``prior`` node asks for a cached prior (a prior read from a file, and ``cache``
    not false; ``prior=zero`` and ``prior=oracle`` read none and are never cached)."""
    return (
        bool(spec)
        and spec.get("name", "none") not in ("none", "zero", "oracle")
        and bool(spec.get("cache", True))
    )


def attach_prior_cache(
    net: nn.Module, spec: Mapping[str, Any], datamodule: Any, device: torch.device | str
) -> PriorCache | None:
    """Fill the cache of ``net``'s prior for the training and validation splits of
    ``datamodule`` (a :class:`~fusion_depth.runner.datamodule.DepthDataModule`) and have its
    loaders read it; None (and nothing done) where ``net`` has no prior or ``spec`` (the
    ``prior`` node) sets ``cache: false``."""
    prior = getattr(net, "prior", None)
    if prior is None or not uses_prior_cache(spec):
        return None
    cache = PriorCache(spec)
    splits = [(split, datamodule.dataset(split)) for split in CACHED_SPLITS]
    fill_prior_caches(cache, prior, splits, device)
    datamodule.prior_cache = cache
    return cache
