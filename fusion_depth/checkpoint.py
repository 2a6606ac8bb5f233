"""Loading a trained model back from a checkpoint, without executing code from the file.

Checkpoints are read with ``torch.load(weights_only=True)``, which only rebuilds tensors and
plain containers. The network is rebuilt from the run config that training stores in every
checkpoint (``fusion_depth_config``), using only its known ``model.net`` keys: a ``_target_``
in the file is never imported or called.
"""

from __future__ import annotations

import os
import pickle
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from fusion_depth.models import DepthNet
from fusion_depth.runs import write_atomic

CONFIG_KEY = "fusion_depth_config"
RUN_KEY = "fusion_depth_run"
READER_NAMESPACE = "fusion_depth.data."  # the only reader targets a checkpoint may name
# The DepthNet constructor arguments a checkpoint may set (everything else in the file is ignored).
_NET_KEYS = (
    "backbone",
    "fusion",
    "min_depth",
    "max_depth",
    "depth_scale",
    "sparse_encoding",
)


class CheckpointError(ValueError):
    """A checkpoint that cannot be used as asked; the message names the file and the problem."""


@dataclass
class LoadedModel:
    """A network rebuilt from a checkpoint, with the run config it was trained with."""

    net: DepthNet
    config: dict[str, Any]
    path: Path
    run: dict[str, Any] | None = None  # the training run's identity, when train recorded it

    @property
    def fusion(self) -> str:
        return self.config["fusion"]["mode"]

    @property
    def backbone(self) -> str:
        return self.config["backbone"]["name"]


def load_weights_only(
    path: str | os.PathLike, map_location: Any = "cpu", mmap: bool = False
) -> Any:
    """``torch.load(weights_only=True)`` of ``path``, with errors naming the file (``mmap``:
    tensors stay on disk until touched, for reading a checkpoint's small entries)."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path={path}: no such file")
    try:
        return torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as err:
        unsupported = re.search(r"Unsupported global: GLOBAL (\S+)", str(err))
        if unsupported is None:
            raise CheckpointError(f"ckpt_path={path}: not a readable PyTorch checkpoint") from err
        raise CheckpointError(
            f"ckpt_path={path}: refused to load; it holds a {unsupported.group(1)} object, and "
            "weights-only loading never runs code from a file to rebuild objects"
        ) from err
    except (RuntimeError, EOFError, OSError) as err:
        raise CheckpointError(
            f"ckpt_path={path}: not a readable PyTorch checkpoint ({err})"
        ) from err


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """The checkpoint's contents (weights-only load onto the CPU), with errors naming the file."""
    path = Path(path).expanduser()
    checkpoint = load_weights_only(path)
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint:
        raise CheckpointError(f"ckpt_path={path}: not a Lightning checkpoint (no 'state_dict')")
    if not isinstance(checkpoint.get(CONFIG_KEY), dict):
        raise CheckpointError(
            f"ckpt_path={path}: no '{CONFIG_KEY}' in it; only checkpoints written by "
            "fusion_depth.train can be evaluated (they record the run config)"
        )
    return checkpoint


def check_expected(
    config: dict[str, Any], path: Path, fusion: str | None = None, backbone: str | None = None
) -> None:
    """Fail when the caller asked for another fusion mode or backbone than the checkpoint has."""
    trained = {"fusion": config["fusion"]["mode"], "backbone": config["backbone"]["name"]}
    for key, wanted in (("fusion", fusion), ("backbone", backbone)):
        if wanted is not None and wanted != trained[key]:
            raise CheckpointError(
                f"ckpt_path={path} was trained with {key}={trained[key]}, but {key}={wanted} "
                f"was asked for: drop the {key}= override or pick a {key}={wanted} checkpoint"
            )


def load_model(
    path: str | os.PathLike, fusion: str | None = None, backbone: str | None = None
) -> LoadedModel:
    """Rebuild the DepthNet of a training checkpoint and load its weights (eval mode, CPU).

    ``fusion``/``backbone``, when given, must match what the checkpoint was trained with.
    """
    path = Path(path).expanduser()
    checkpoint = read_checkpoint(path)
    config = checkpoint[CONFIG_KEY]
    try:
        net_config = config["model"]["net"]
        config["fusion"]["mode"], config["backbone"]["name"]  # noqa: B018 - presence check
    except (KeyError, TypeError) as err:
        raise CheckpointError(f"ckpt_path={path}: its run config lacks {err}") from err
    check_expected(config, path, fusion, backbone)
    # pretrained=False: the checkpoint's weights replace ImageNet's, which need not be on disk.
    net = DepthNet(**{k: net_config[k] for k in _NET_KEYS if k in net_config}, pretrained=False)
    state = {
        key[len("net.") :]: value
        for key, value in checkpoint["state_dict"].items()
        if key.startswith("net.")
    }
    expected = net.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong_shape = sorted(
        k for k in set(state) & set(expected) if state[k].shape != expected[k].shape
    )
    if missing or unexpected or wrong_shape:
        what = ", ".join(
            f"{name}: {keys[:3]}{' …' if len(keys) > 3 else ''}"
            for name, keys in (
                ("missing", missing),
                ("unexpected", unexpected),
                ("wrong shape", wrong_shape),
            )
            if keys
        )
        raise CheckpointError(
            f"ckpt_path={path}: its weights do not fit backbone={config['backbone']['name']} "
            f"fusion={config['fusion']['mode']}, which its run config names ({what})"
        )
    net.load_state_dict(state)
    run = checkpoint.get(RUN_KEY)
    return LoadedModel(
        net=net.eval(), config=config, path=path, run=run if isinstance(run, dict) else None
    )


def dataset_config(loaded: LoadedModel, chosen: Any | None) -> dict[str, Any]:
    """The dataset block to score or predict on: ``chosen`` (a ``dataset=`` choice composed from
    ``conf/``) when given, else the one the checkpoint was trained on.

    A checkpoint's block names its reader by ``_target_``; only readers of this package
    (``fusion_depth.data.*``) are accepted, so a crafted file cannot make us call anything else.
    """
    if chosen is not None:
        if "reader" not in chosen:  # e.g. experiment=smoke sets dataset sizes without a dataset=
            raise ValueError(
                f"dataset settings {sorted(chosen)} were given but no dataset was chosen: add "
                "dataset=<name> (e.g. dataset=procedural) to use them, or leave them out to use "
                f"the dataset ckpt_path={loaded.path} was trained on"
            )
        return chosen
    block = loaded.config.get("dataset")
    target = (block or {}).get("reader", {}).get("_target_", "")
    if not isinstance(target, str) or not target.startswith(READER_NAMESPACE):
        raise CheckpointError(
            f"ckpt_path={loaded.path}: its dataset reader {target!r} is not one of "
            f"{READER_NAMESPACE}*; pass dataset=<name> to choose the dataset explicitly"
        )
    return block


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint writer and reader, made safe for runs that get killed.

    A checkpoint is written to a temporary sibling, flushed to disk and renamed over the old
    one, so a kill, a dead node or a full disk leaves the previous checkpoint intact rather
    than a truncated one (Lightning's own writer opens the target itself). Reading is
    weights-only, whatever the caller asks for: resuming never runs code from a file.
    """

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None
    ) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options")

        def write(tmp: Path) -> None:
            with tmp.open("wb") as f:
                torch.save(checkpoint, f)
                f.flush()
                os.fsync(f.fileno())

        try:
            write_atomic(path, write, suffix=".ckpt.tmp")
        except OSError as err:
            raise OSError(
                err.errno,
                f"{path}: could not write the checkpoint ({err.strerror or err}); "
                "the previous checkpoint there, if any, is untouched",
            ) from err

    def load_checkpoint(
        self, path: Any, map_location: Any | None = None, weights_only: bool | None = None
    ) -> dict[str, Any]:
        return load_weights_only(path, map_location=map_location)
