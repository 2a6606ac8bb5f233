"""Pretrained timm backbones exposed as DenseDepth-style multi-scale encoders.

The decoder needs the features at strides 2, 4, 8, 16 (skips) and 32 (bottleneck). Two ways to
get them (``taps``):

* ``paper`` (``backbone=densenet169|resnet50``): the paper's exact taps. DenseDepth taps
  DenseNet-169 after conv0's ReLU, after pool0, after transitions 1 and 2, and at norm5; timm's
  ``features_only`` taps different points (the dense blocks), so we walk the backbone's own stages
  in order and keep the outputs of the named ones (:data:`ENCODER_SPECS`).
* ``pyramid`` (``backbone=timm backbone.name=<any timm model>``): the model's own feature pyramid,
  ``timm.create_model(name, features_only=True, out_indices=...)``, the deepest level at each of
  the strides 4, 8, 16, 32 (and 2 where the model has one). A model whose first level is at
  stride 4 (ConvNeXt, Swin-like hierarchies, FastViT, ...) gets a small learned stem for the
  stride-2 skip (see :class:`Encoder`).
"""

from __future__ import annotations

import contextlib
import difflib
import logging
import os
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import timm
import torch
from torch import nn

from fusion_depth.errors import ArgumentError, ArgumentFileError
from fusion_depth.utils.schema import (
    BOOLEAN,
    Schema,
)

log = logging.getLogger(__name__)


class WeightsUnavailableError(ArgumentError, RuntimeError):
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
    # timm's ResNet-10-T (one block per stage, a three-conv stem): the built-in dataset's recipe
    # trains it from random weights 1.45× faster per sample than ResNet-18
    # (docs/results/built-in-recipe.md).
    "resnet10t": EncoderSpec("", ("act1", "layer1", "layer2", "layer3", "layer4")),
}

# How the decoder's five inputs are taken from the backbone (see the module docstring).
TAPS: tuple[str, ...] = ("paper", "pyramid")
STRIDES: tuple[int, ...] = (2, 4, 8, 16, 32)  # the decoder's contract, finest first
_PROBE_SIZE = 64  # side of the all-zero image each encoder is checked on when built


def check_backbone_name(name: Any, taps: str = "paper") -> None:
    """Refuse a backbone ``name`` the encoder cannot build with ``taps``, in one line, before
    anything is built (no model is created; this takes milliseconds).

    ``paper``: one of :data:`ENCODER_SPECS`. ``pyramid``: a timm architecture
    (``timm.list_models()``), optionally with a pretrained tag (``convnext_tiny.fb_in22k``, as
    ``timm.list_pretrained()`` lists them). Whether the model has a usable feature pyramid is only
    known once it is built (:class:`Encoder` refuses it then).

    Raises:
        ArgumentError: ``name=...`` (or ``taps=...``), with a did-you-mean for a misspelt timm
            name.
    """

    def error(rest: str, argument: str = "name") -> ArgumentError:
        return ArgumentError("{" + argument + "}" + rest, argument, owner=check_backbone_name)

    if taps == "paper":
        if name not in ENCODER_SPECS:
            raise error(
                f"={name}: expected one of {', '.join(sorted(ENCODER_SPECS))} (the paper's "
                "taps); any other timm model: backbone=timm"
            )
        return
    if taps != "pyramid":
        raise error(f"={taps}: expected one of {', '.join(TAPS)}", "taps")
    if not isinstance(name, str) or not name:
        raise error(f"={name}: expected a timm model name (timm.list_models())")
    arch, tag = timm.models.split_model_name_tag(name)
    known = timm.list_pretrained(f"{arch}.*") if tag else timm.list_models()
    if (name if tag else arch) in known:
        return
    what = "not a timm model" if arch not in timm.list_models() else f"no pretrained tag {tag!r}"
    close = difflib.get_close_matches(name, known or timm.list_pretrained(), n=1)
    hint = f" (did you mean {close[0]}?)" if close else ""
    raise error(
        f"={name}: {what}{hint}; expected a name from timm.list_models() or timm.list_pretrained()"
    )


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


def create_timm_model(name: str, pretrained: bool, weights: str | None, **kwargs: Any) -> nn.Module:
    """Create ``name`` through timm; weights from a local file, the hub cache, or the hub.

    ``kwargs`` go to ``timm.create_model`` (e.g. ``features_only=True, out_indices=(...)``: timm
    loads the weights into the whole model, classifier dropped, before wrapping it, so the file
    and missing-keys checks below hold for a feature pyramid too).

    Raises:
        ArgumentError: ``weights`` is not a checkpoint file, or not a state dict of ``name`` (a
            key the model needs is missing, or a shape differs).
        ArgumentFileError: ``weights`` does not exist (a FileNotFoundError).
        WeightsUnavailableError: ``pretrained`` without a cached or downloadable checkpoint.
    """
    if weights:
        path = Path(weights).expanduser()
        if path.suffix not in {".safetensors", ".pth", ".pt", ".bin"}:
            raise ArgumentError(
                f"{{weights}}={weights}: expected a .safetensors, .pth, .pt or .bin file",
                "weights",
                owner=create_timm_model,
            )
        if not path.is_file():
            raise ArgumentFileError(
                f"{{weights}}={weights}: no such file", "weights", owner=create_timm_model
            )
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
                    **kwargs,
                )
            except RuntimeError as err:
                raise ArgumentError(
                    f"{{weights}}={weights}: not a state dict for {name} ({err})",
                    "weights",
                    owner=create_timm_model,
                ) from err
        if missing:
            raise ArgumentError(
                f"{{weights}}={weights}: not a state dict for {name}; it lacks {missing[0]}",
                "weights",
                owner=create_timm_model,
            )
        return model
    if not pretrained:
        return timm.create_model(name, pretrained=False, num_classes=0, **kwargs)
    return _create_from_hub(name, **kwargs)


CHECKPOINT_SUFFIX = ".ckpt"  # what train writes: backbone.weights=<it> starts from its encoder


def encoder_state_from_checkpoint(weights: str) -> tuple[dict[str, torch.Tensor], str]:
    """The encoder's weights of a checkpoint ``train`` wrote (read weights-only): the
    ``net.encoder.*`` entries of its state dict, unprefixed, for transfer learning from a
    network trained on other data (``backbone.weights=<file>.ckpt``).

    Returns:
        The state dict and ``weights`` as given (for messages).

    Raises:
        ArgumentFileError: no such file.
        ArgumentError: not a readable checkpoint, or one whose network has no encoder.
    """
    from fusion_depth.utils.checkpoint_file import CheckpointError, read_checkpoint

    path = Path(weights).expanduser()
    if not path.is_file():
        raise ArgumentFileError(f"{{weights}}={weights}: no such file", "weights", owner=Encoder)
    try:
        checkpoint = read_checkpoint(path)
    except CheckpointError as err:
        problem = str(err).partition(": ")[2] or str(err)
        raise ArgumentError(f"{{weights}}={weights}: {problem}", "weights", owner=Encoder) from None
    prefix = "net.encoder."
    state = {
        k.removeprefix(prefix): v
        for k, v in checkpoint["state_dict"].items()
        if k.startswith(prefix)
    }
    if not state:
        raise ArgumentError(
            f"{{weights}}={weights}: its network has no encoder (no {prefix}* weights); expected "
            "a checkpoint of an encoder-decoder network (model=densedepth)",
            "weights",
            owner=Encoder,
        )
    return state, str(weights)


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


def _create_from_hub(name: str, **kwargs: Any) -> nn.Module:
    """ImageNet weights from the local cache, else downloaded; fails fast when offline.
    ``kwargs`` go to ``timm.create_model``."""
    cached = _cached_weights(name)
    if cached is not None:
        return create_timm_model(name, pretrained=True, weights=str(cached), **kwargs)
    reason = "the hub cannot be reached (offline)"
    if _hub_reachable():
        try:
            return timm.create_model(name, pretrained=True, num_classes=0, **kwargs)
        except Exception as err:  # noqa: BLE001 - any failure means "not available here"
            reason = f"the download failed ({type(err).__name__}: {str(err).splitlines()[0]})"
    raise WeightsUnavailableError(
        f"ImageNet weights for backbone '{name}' are not in the local cache and {reason}. "
        f"Either pass a local file with {{weights}}=/path/to/{name}.safetensors (or .pth), "
        "or train from scratch with {pretrained}=false.",
        "weights",
        "pretrained",
        owner=create_timm_model,
    )


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return f"{type(err).__name__}: {text.splitlines()[0][:200]}" if text else type(err).__name__


def _pyramid_levels(info: list[dict[str, Any]], name: str) -> dict[int, int]:
    """stride → position in timm's ``feature_info`` of the level the decoder takes there: the
    deepest one at each of the strides 4, 8, 16, 32, and at 2 where the model has one.

    Raises:
        ValueError: no level at one of the strides 4, 8, 16, 32 (e.g. a ViT: all at 16).
    """
    chosen: dict[int, int] = {}
    for position, level in enumerate(info):
        if level["reduction"] in STRIDES:
            chosen[level["reduction"]] = position  # later levels at one stride are deeper
    if not all(stride in chosen for stride in STRIDES[1:]):
        strides = ", ".join(str(r) for r in sorted({level["reduction"] for level in info}))
        raise ArgumentError(
            f"{{name}}={name}: its feature pyramid has levels at strides {strides}; "
            "expected levels at strides 4, 8, 16 and 32 (and optionally 2) for the DenseDepth "
            "decoder",
            "name",
            owner=Encoder,
        )
    return chosen


class Encoder(nn.Module):
    """A timm backbone returning the five feature maps the DenseDepth decoder takes.

    ``taps="paper"`` runs the stages of a model of :data:`ENCODER_SPECS` in order and keeps the
    outputs of the listed ones (the paper's DenseNet-169/ResNet-50 taps, unchanged).
    ``taps="pyramid"`` takes any timm model that supports ``features_only``: the deepest level of
    its own pyramid at each of the strides 4, 8, 16, 32 (``feature_info``), and at stride 2 where
    it has one (EfficientNet, RegNet, MobileNet: their stem). A model whose first level is at
    stride 4 (ConvNeXt's 4×4 patchify stem has nothing at stride 2) gets a learned stem instead:
    3×3 conv (stride 2, no bias) + BatchNorm + ReLU on the fused input image, ``max(16, C4 // 2)``
    channels for a stride-4 level of C4. The decoder's last up-block needs a stride-2 skip to
    reach half resolution with detail finer than stride 4; this stem is what the paper's taps
    give there (DenseNet's conv0 → norm0 → ReLU, ResNet's conv1 → bn1 → act1), small, and trained
    from scratch with the decoder.

    Args:
        name: a timm model name (``paper``: a key of :data:`ENCODER_SPECS`).
        pretrained: ImageNet weights from the local hub cache, else the hub.
        weights: a local ``.safetensors``/``.pth``/``.pt``/``.bin`` state dict of ``name``
            (timm/torchvision layout; the classifier may be in it), or a ``.ckpt`` that
            ``train`` wrote, whose encoder (of the same ``name`` and taps) is loaded: transfer
            learning from a network trained on other data.
        taps: ``paper`` or ``pyramid`` (see above).

    Shape:
        - input: (B, 3, H, W), the fused, normalised image; H and W multiples of 32.
        - output: five maps (B, C_i, H / s, W / s) for s = 2, 4, 8, 16, 32 and C_i =
          :attr:`channels` ``[i]``, NCHW (an NHWC timm pyramid, e.g. MambaOut's, is permuted).

    Raises:
        ValueError: ``name`` is no backbone for ``taps`` (:func:`check_backbone_name`), timm
            cannot build its ``features_only`` pyramid, the pyramid lacks a level at stride 4, 8,
            16 or 32 (ViT, LeViT), or the model cannot run on a 64×64 image (fixed input sizes:
            ViT, Swin).
        FileNotFoundError, RuntimeError, WeightsUnavailableError: see
            :func:`create_timm_model`.
    """

    def __init__(
        self,
        name: str = "densenet169",
        pretrained: bool = False,
        weights: str | None = None,
        taps: str = "paper",
    ) -> None:
        super().__init__()
        check_backbone_name(name, taps)
        trained = None  # a checkpoint train wrote: its encoder's weights, loaded once built
        if weights and Path(weights).suffix == CHECKPOINT_SUFFIX:
            trained, weights, pretrained = encoder_state_from_checkpoint(weights), None, False
        self.name = name
        self.body: nn.Module | None = None  # pyramid: timm's features_only model
        self.stem: nn.Module | None = None  # pyramid without a stride-2 level: the learned stem
        self.nhwc = False
        if taps == "paper":
            spec = ENCODER_SPECS[name]
            model = create_timm_model(name, pretrained, weights)
            container = model.get_submodule(spec.container) if spec.container else model
            names = [n for n, _ in container.named_children()]
            last = names.index(spec.taps[-1])
            # Only the stages up to the bottleneck; pooling and classifier are dropped.
            self.stages = nn.ModuleDict({n: container.get_submodule(n) for n in names[: last + 1]})
            self.taps: tuple[str, ...] = spec.taps
        else:
            model = self._build_pyramid(name, pretrained, weights)
        self.mean = tuple(model.pretrained_cfg.get("mean", (0.485, 0.456, 0.406)))
        self.std = tuple(model.pretrained_cfg.get("std", (0.229, 0.224, 0.225)))
        probe = torch.zeros(1, 3, _PROBE_SIZE, _PROBE_SIZE)
        with torch.no_grad():
            was_training = self.training
            self.eval()
            try:
                feats = self(probe)
            except Exception as err:  # noqa: BLE001 - any failure: the model cannot run here
                raise ArgumentError(
                    f"{{name}}={name}: cannot run on a {_PROBE_SIZE}×{_PROBE_SIZE} image "
                    f"({_first_line(err)}); expected a model that takes any size that is a "
                    "multiple of 32 (fixed-size models such as ViT or Swin are not supported)",
                    "name",
                    owner=Encoder,
                ) from None
            finally:
                self.train(was_training)
        sizes = [tuple(f.shape[-2:]) for f in feats]
        wanted = [(_PROBE_SIZE // s, _PROBE_SIZE // s) for s in STRIDES]
        if sizes != wanted:
            raise ArgumentError(
                f"{{name}}={name}: its feature maps on a {_PROBE_SIZE}×{_PROBE_SIZE} image "
                f"are {sizes}; expected strides 2, 4, 8, 16, 32, i.e. {wanted}",
                "name",
                owner=Encoder,
            )
        self.channels: tuple[int, ...] = tuple(f.shape[1] for f in feats)
        if trained is not None:
            self._load_trained(trained[0], trained[1])

    def _load_trained(self, state: dict[str, torch.Tensor], weights: str) -> None:
        """Load the encoder of a checkpoint ``train`` wrote (strict: the same backbone)."""
        expected = self.state_dict()
        for key, value in expected.items():
            if key not in state:
                raise ArgumentError(
                    f"{{weights}}={weights}: its encoder has no {key}; expected a checkpoint of "
                    f"a network with backbone={self.name} (the same taps)",
                    "weights",
                    owner=Encoder,
                )
            if state[key].shape != value.shape:
                raise ArgumentError(
                    f"{{weights}}={weights}: its encoder's {key} is {list(state[key].shape)}, "
                    f"expected {list(value.shape)} (backbone={self.name})",
                    "weights",
                    owner=Encoder,
                )
        extra = sorted(set(state) - set(expected))
        if extra:
            raise ArgumentError(
                f"{{weights}}={weights}: its encoder has {extra[0]}, which backbone={self.name} "
                "has not; expected a checkpoint of a network with that backbone",
                "weights",
                owner=Encoder,
            )
        self.load_state_dict(state)

    def _build_pyramid(self, name: str, pretrained: bool, weights: str | None) -> nn.Module:
        """Set :attr:`body` (and :attr:`stem`, :attr:`taps`, :attr:`nhwc`) from timm's
        ``features_only`` model of ``name``; returns it (for its ``pretrained_cfg``)."""
        # The levels are only known from a built model: a random-init one first (cheap), which
        # is kept when it already outputs exactly the chosen levels and no weights are wanted.
        try:
            probe = timm.create_model(name, pretrained=False, features_only=True)
        except Exception as err:  # noqa: BLE001 - any failure means "no feature pyramid"
            raise ArgumentError(
                f"{{name}}={name}: timm cannot build its feature pyramid "
                f"(features_only=True: {_first_line(err)}); expected a model that supports "
                "features_only",
                "name",
                owner=Encoder,
            ) from None
        info = probe.feature_info.info
        chosen = _pyramid_levels(info, name)
        out_indices = tuple(chosen[s] for s in STRIDES if s in chosen)
        if out_indices == tuple(probe.feature_info.out_indices) and not (pretrained or weights):
            body = probe
        else:
            del probe
            body = create_timm_model(
                name, pretrained, weights, features_only=True, out_indices=out_indices
            )
        self.body = body
        fmt = getattr(body, "output_fmt", "NCHW")
        self.nhwc = getattr(fmt, "value", fmt) == "NHWC"
        taps = [str(info[i]["module"]) for i in out_indices]
        if 2 not in chosen:
            width = max(16, int(info[chosen[4]]["num_chs"]) // 2)
            self.stem = nn.Sequential(
                nn.Conv2d(3, width, 3, stride=2, padding=1, bias=False),
                nn.BatchNorm2d(width),
                nn.ReLU(inplace=True),
            )
            taps.insert(0, "stem (learned)")
        self.taps = tuple(taps)
        return body

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B, 3, H, W) → five maps at strides 2, 4, 8, 16, 32 (see the class docstring)."""
        if self.body is not None:
            features = list(self.body(x))
            if self.nhwc:
                features = [f.permute(0, 3, 1, 2) for f in features]
            if self.stem is not None:
                features.insert(0, self.stem(x))
            return features
        features = []
        for name, stage in self.stages.items():
            x = stage(x)
            if name in self.taps:
                features.append(x)
        return features


# What :class:`Encoder`'s arguments besides its name accept (fusion_depth.utils.schema).
ARGUMENT_RULES: Schema = {"pretrained": BOOLEAN}
