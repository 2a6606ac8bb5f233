"""Pretrained timm backbones exposed as DenseDepth-style multi-scale encoders.

The decoder needs the features at strides 2, 4, 8, 16 (skips) and 32 (bottleneck). DenseDepth taps
DenseNet-169 after conv0's ReLU, after pool0, after transitions 1 and 2, and at norm5; timm's
``features_only`` taps different points (the dense blocks), so we walk the backbone's own stages
in order and keep the outputs of the named ones.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlparse

import timm
import torch
from torch import nn

log = logging.getLogger(__name__)


class WeightsUnavailableError(RuntimeError):
    """ImageNet weights were asked for but can be had neither from disk nor from the hub."""


@dataclass(frozen=True)
class EncoderSpec:
    """Where the stages live inside a timm model and which of them feed the decoder."""

    container: str  # attribute holding the stages in forward order ("" = the model itself)
    taps: tuple[str, str, str, str, str]  # strides 2, 4, 8, 16, 32


ENCODER_SPECS: dict[str, EncoderSpec] = {
    "densenet169": EncoderSpec(
        "features", ("norm0", "pool0", "transition1", "transition2", "norm5")
    ),
    "densenet121": EncoderSpec(
        "features", ("norm0", "pool0", "transition1", "transition2", "norm5")
    ),
    "resnet50": EncoderSpec("", ("act1", "layer1", "layer2", "layer3", "layer4")),
    "resnet18": EncoderSpec("", ("act1", "layer1", "layer2", "layer3", "layer4")),
}


@contextlib.contextmanager
def _missing_keys_reported() -> Iterator[list[str]]:
    """Collect timm's "Missing keys" report (logged at INFO) while loading a checkpoint."""
    found: list[str] = []

    class _Handler(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            message = record.getMessage()
            if message.startswith("Missing keys"):
                found.append(message.split(")")[0].removeprefix("Missing keys (")[:300])

    timm_log = logging.getLogger("timm.models._builder")
    handler, level = _Handler(logging.INFO), timm_log.level
    timm_log.addHandler(handler)
    timm_log.setLevel(logging.INFO)
    try:
        yield found
    finally:
        timm_log.removeHandler(handler)
        timm_log.setLevel(level)


def _create_timm_model(name: str, pretrained: bool, weights: str | None) -> nn.Module:
    """Create ``name`` through timm; weights from a local file, the hub cache, or the hub."""
    if weights:
        path = Path(weights).expanduser()
        if path.suffix not in {".safetensors", ".pth", ".pt", ".bin"}:
            raise ValueError(
                f"backbone.weights={weights}: expected a .safetensors, .pth, .pt or .bin file"
            )
        if not path.is_file():
            raise FileNotFoundError(f"backbone.weights={weights}: no such file")
        # timm's loader applies the model's checkpoint filter (key remapping) and drops the
        # classifier because num_classes=0 differs from the checkpoint's. It then loads
        # non-strictly, so a checkpoint of another architecture would load nothing in silence:
        # any key the backbone misses is an error.
        with _missing_keys_reported() as missing:
            try:
                model = timm.create_model(
                    name,
                    pretrained=True,
                    num_classes=0,
                    pretrained_cfg_overlay={"file": str(path), "hf_hub_id": None, "url": None},
                )
            except RuntimeError as err:
                raise RuntimeError(
                    f"backbone.weights={weights}: not a state dict for {name} ({err})"
                ) from err
        if missing:
            raise RuntimeError(
                f"backbone.weights={weights}: not a state dict for {name}; it lacks {missing[0]}"
            )
        return model
    if not pretrained:
        return timm.create_model(name, pretrained=False, num_classes=0)
    return _create_from_hub(name)


def _hub_reachable(timeout: float = 3.0) -> bool:
    """A TCP connect to the hub: huggingface_hub retries with back-off for minutes offline."""
    host = urlparse(os.environ.get("HF_ENDPOINT", "https://huggingface.co")).hostname
    try:
        with socket.create_connection((host or "huggingface.co", 443), timeout=timeout):
            return True
    except OSError:
        return False


def _cached_weights(name: str) -> Path | None:
    """The default ImageNet checkpoint of ``name`` if a previous download left it on disk."""
    from huggingface_hub import try_to_load_from_cache

    cfg = timm.models.get_pretrained_cfg(name)
    if cfg is None:
        return None
    if cfg.hf_hub_id:
        for filename in (cfg.hf_hub_filename or "model.safetensors", "pytorch_model.bin"):
            found = try_to_load_from_cache(cfg.hf_hub_id, filename)
            if isinstance(found, str):
                return Path(found)
    if cfg.url:
        path = Path(torch.hub.get_dir()) / "checkpoints" / Path(urlparse(cfg.url).path).name
        if path.is_file():
            return path
    return None


def _create_from_hub(name: str) -> nn.Module:
    """ImageNet weights from the local cache, else downloaded; fails fast when offline."""
    cached = _cached_weights(name)
    if cached is not None:
        return _create_timm_model(name, pretrained=True, weights=str(cached))
    reason = "the hub cannot be reached (offline)"
    if _hub_reachable():
        try:
            return timm.create_model(name, pretrained=True, num_classes=0)
        except Exception as err:  # noqa: BLE001 - any failure means "not available here"
            reason = f"the download failed ({type(err).__name__}: {str(err).splitlines()[0]})"
    raise WeightsUnavailableError(
        f"ImageNet weights for backbone '{name}' are not in the local cache and {reason}. "
        f"Either pass a local file with backbone.weights=/path/to/{name}.safetensors (or .pth), "
        "or train from scratch with backbone.pretrained=false."
    )


class Encoder(nn.Module):
    """Runs a timm backbone's stages in order and returns the five tapped feature maps."""

    def __init__(
        self, name: str = "densenet169", pretrained: bool = False, weights: str | None = None
    ) -> None:
        super().__init__()
        if name not in ENCODER_SPECS:
            raise ValueError(f"backbone.name={name!r}: expected one of {sorted(ENCODER_SPECS)}")
        spec = ENCODER_SPECS[name]
        model = _create_timm_model(name, pretrained, weights)
        container = model.get_submodule(spec.container) if spec.container else model
        names = [n for n, _ in container.named_children()]
        last = names.index(spec.taps[-1])
        # Only the stages up to the bottleneck; pooling and classifier are dropped.
        self.stages = nn.ModuleDict({n: container.get_submodule(n) for n in names[: last + 1]})
        self.taps = spec.taps
        self.name = name
        self.mean = tuple(model.pretrained_cfg.get("mean", (0.485, 0.456, 0.406)))
        self.std = tuple(model.pretrained_cfg.get("std", (0.229, 0.224, 0.225)))
        with torch.no_grad():
            was_training = self.training
            self.eval()
            feats = self(torch.zeros(1, 3, 64, 64))
            self.train(was_training)
        self.channels: tuple[int, ...] = tuple(f.shape[1] for f in feats)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        features = []
        for name, stage in self.stages.items():
            x = stage(x)
            if name in self.taps:
                features.append(x)
        return features
