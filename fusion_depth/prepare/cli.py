"""Build a dataset's cache once, before training: ``python -m fusion_depth.prepare dataset=...``.

Takes the same configuration as ``fusion_depth.train`` and builds every split the dataset's
reader would build on first use (projection, filling, resizing), so training epochs only read
small files. The dataset is the one training with the same overrides reads: a model's dataset
recipe (``prepare model=radarnet``) and ``experiment=`` apply as they do there
(:func:`~fusion_depth.config.recipes.register_dataset_recipes`). Running it again with the
same settings does nothing; an interrupted run continues where it stopped (see
:mod:`fusion_depth.data.cache`).

Unlike training, which stops at the first frame whose files cannot be read, prepare goes on: it
logs ``skipped <frame id>: <reason>`` for each broken frame (a corrupt, truncated or missing
file, a directory where a file should be), prepares every other frame of every split, prints one
line per split (``train: 3 of 4 frames prepared; skipped 1: train/a02``) and exits with status
1. A split with a skipped frame is not marked prepared, so training still refuses it, naming
the file. Running prepare again reuses every frame already written to that cache and prepares
only the rest; note that CARLA and Top-View caches are keyed by every file's size and time, so
replacing a file there starts a new cache. Problems that are not about one frame (a missing
dataset folder, a bad setting, an unwritable cache) fail at once, as in training; a full disk in
one line naming the cache. A split already prepared is verified (:func:`~fusion_depth.data.
cache.is_prepared`): a frame whose source file changed is prepared again. Ctrl-C stops every
worker within a second or two and prints one line (exit status 130); the frames finished are
kept, nothing else is left.

``prepare.workers`` (default ``auto``: every core the process may use) prepares frames in that
many processes; ``prepare.shard=I prepare.num_shards=N`` prepares every N-th frame from the
I-th, for a multirun across machines. A shard whose frames are done while others' are not prints
how far each split is and exits 0; the last one writes the index (see
:mod:`fusion_depth.data.cache`).
"""

from __future__ import annotations

import logging
import sys
from typing import Any

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from fusion_depth.config import target_accepts, validate_dataset_config
from fusion_depth.config.hydra_main import hydra_main
from fusion_depth.data import SPLITS
from fusion_depth.data.cache import (
    CacheFullError,
    IncompleteSplitError,
    PrepareOptions,
    SkippedFramesError,
    prepare_options,
    usable_cores,
)

log = logging.getLogger(__name__)


def prepare_options_of(cfg: DictConfig) -> PrepareOptions:
    """The :class:`~fusion_depth.data.cache.PrepareOptions` of ``cfg.prepare`` (``workers:
    auto``: every core this process may use; a config without ``prepare``, e.g. training's:
    one worker, no shards); a bad value fails naming its key."""
    settings = cfg.get("prepare") or {}
    workers = settings.get("workers", 1)
    if workers == "auto":
        workers = usable_cores()
    return PrepareOptions(
        workers=workers,
        shard=settings.get("shard", 0),
        num_shards=settings.get("num_shards", 1),
        finish_sharded=True,
    )


def prepare(cfg: DictConfig) -> dict[str, int]:
    """Builds (or finds) every split of ``cfg.dataset``; returns the frame count per split.

    Only ``dataset`` and ``prepare`` are checked
    (:func:`~fusion_depth.config.validate_dataset_config`): the rest of the config is training's,
    and leaving the models and the trainer unimported keeps the start-up short. Readers that
    prepare a cache are built with ``on_error="skip"`` (the procedural reader, which generates its
    frames, takes no such argument).

    ``cfg.prepare`` (:func:`prepare_options_of`) sets the workers and this process's shard.

    Raises:
        SkippedFramesError: some frames could not be prepared; every other frame was. Its
            ``reports`` hold one :class:`~fusion_depth.data.cache.SplitReport` per split
            folder (KITTI's test split is its val folder). Each is also logged.
        IncompleteSplitError: this shard's frames are all done, and other shards' are not yet
            (its ``splits``: each split still waiting).
        CacheFullError: the cache's disk is full.
    """
    validate_dataset_config(cfg)
    spread = prepare_options_of(cfg)
    reader = instantiate(cfg.dataset.reader)
    options = {"on_error": "skip"} if target_accepts(cfg.dataset.reader, "on_error") else {}
    counts = {}
    for split in SPLITS:
        try:
            with prepare_options(spread):
                dataset = reader(split=split, **options)
        except SkippedFramesError as err:
            # A reader prepares all of its splits when the first is built, so err covers them
            # all; building the next split would only retry (and log) the same broken frames.
            for report in err.reports:
                if report.skipped:
                    log.warning("%s %s (not marked prepared)", cfg.dataset.name, report.line())
                else:
                    log.info("%s %s", cfg.dataset.name, report.line())
            raise
        counts[split] = len(dataset)
        log.info("%s %s: %d frames ready", cfg.dataset.name, split, counts[split])
    return counts


def cached_prior(cfg: DictConfig) -> Any:
    """With ``prior=<name>`` (and ``prior.cache`` not false): the prior, built (and its settings
    checked) before any frame is prepared; None without one.

    Raises:
        ConfigError: a ``prior.*`` value it cannot take (naming the key).
        ArgumentError: the prior cannot be built (naming ``prior.weights``).
    """
    spec = OmegaConf.to_container(cfg.prior, resolve=True) if cfg.get("prior") else None
    if not spec or spec.get("name", "none") == "none":
        return None  # before any import: most prepares need no torch (seconds of start-up)
    from fusion_depth.runner.prior_cache import uses_prior_cache

    if not uses_prior_cache(spec):
        return None
    from fusion_depth.models.depth_prior import ARGUMENT_RULES, build_prior
    from fusion_depth.utils.config_values import check_schema

    check_schema(cfg, {f"prior.{key}": rule for key, rule in ARGUMENT_RULES.items()})
    return build_prior(
        spec["name"],
        spec["weights"],
        spec.get("input_size"),
        kind=spec.get("kind"),
        max_depth=spec.get("max_depth"),
    )


def prepare_prior(cfg: DictConfig, prior: Any) -> int:
    """The prior of every training and validation frame computed into its cache
    (:mod:`fusion_depth.runner.prior_cache`), where training reads it; the frames computed (0:
    all were cached)."""
    import torch

    from fusion_depth.runner.datamodule import IndexedDataset
    from fusion_depth.runner.prior_cache import CACHED_SPLITS, PriorCache, fill_prior_caches

    reader = instantiate(cfg.dataset.reader)
    frames = [(split, IndexedDataset(reader(split=split))) for split in CACHED_SPLITS]
    device = "cuda" if torch.cuda.is_available() else "cpu"
    spec = OmegaConf.to_container(cfg.prior, resolve=True)
    return fill_prior_caches(PriorCache(spec), prior, frames, device)


@hydra_main("prepare")
def main(cfg: DictConfig) -> None:
    """Entry point: prints the frames per split; exits with status 1 when frames were skipped
    (after printing one line per split)."""
    prior = cached_prior(cfg)  # a bad prior fails before any frame is prepared
    try:
        counts = prepare(cfg)
        computed = None if prior is None else prepare_prior(cfg, prior)
    except KeyboardInterrupt:
        print(
            "prepare: interrupted (Ctrl-C); the frames finished so far are kept: run the same "
            "command again to go on",
            file=sys.stderr,
        )
        sys.exit(130)
    except IncompleteSplitError as err:
        shard = f"shard {cfg.prepare.shard} of {cfg.prepare.num_shards}"
        print(f"{shard}: its frames are prepared; waiting for the other shards:")
        for split in err.splits:
            print(f"  {split.split_dir.name}: {split.done} of {split.total} frames")
        hint = next((split.hint for split in err.splits if split.hint), None)
        if hint:
            print(f"warning: {hint}", file=sys.stderr)
        return
    except CacheFullError as err:
        print(f"error: {err.strerror}", file=sys.stderr)
        sys.exit(1)
    except SkippedFramesError as err:
        for report in err.reports:
            print(report.line())
        skipped = sum(len(report.skipped) for report in err.reports)
        print(
            f"{skipped} frame(s) skipped, so their splits are not marked prepared (training "
            "refuses them): fix or remove their files and run prepare again (frames already "
            "prepared are kept)"
        )
        sys.exit(1)
    print(", ".join(f"{split}: {n} frames" for split, n in counts.items()))
    if computed is not None:
        print(f"prior={cfg.prior.name}: {computed} frames computed, the others were cached")
