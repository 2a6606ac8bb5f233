"""Frozen monocular depth priors: networks that give a relative (affine-invariant) inverse depth
per frame, which :mod:`fusion_depth.models.alignment` makes metric with the frame's radar.

:class:`DepthAnythingPrior` is Depth Anything V2 (Yang et al., NeurIPS 2024) as ``transformers``
builds it (``DepthAnythingForDepthEstimation``), with weights read from local files only, never
downloaded: a transformers folder (``config.json`` and ``model.safetensors``, as
``depth-anything/Depth-Anything-V2-Small-hf`` ships) or the authors' ``.pth`` checkpoint
(``depth_anything_v2_vits.pth``, ``_vitb``, ``_vitl``), whose names are mapped to transformers'
as its conversion script ``convert_depth_anything_to_hf.py`` does. Licences: the Small weights
are Apache-2.0; Base and Large are CC-BY-NC-4.0 (the authors' README).

``transformers`` is an optional extra (``pip install -e ".[prior]"`` in a clone), imported on
first use.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from fusion_depth.errors import (
    ArgumentError,
    ArgumentFileError,
    MissingDependencyError,
    check_choice,
)
from fusion_depth.utils.checkpoint_file import CheckpointError
from fusion_depth.utils.schema import BOOLEAN, POSITIVE_INT, PROBABILITY, Rule, Schema

log = logging.getLogger(__name__)

PATCH = 14  # DINOv2's patch: the prior's input is resized to a multiple of it
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
# Which blocks feed the head, by the encoder's depth: ViT-S and ViT-B have 12, ViT-L 24
# (the authors' ``intermediate_layer_idx``, 1-based as transformers counts them).
OUT_INDICES = {12: (3, 6, 9, 12), 24: (5, 12, 18, 24)}
HEAD_WIDTH = 64  # DINOv2's attention heads are 64 wide: heads = embedding width / 64

# The authors' names → transformers' (the conversion script's rename_key list), as regexes.
_RENAMES: tuple[tuple[str, str], ...] = (
    (r"^pretrained\.cls_token$", "backbone.embeddings.cls_token"),
    (r"^pretrained\.mask_token$", "backbone.embeddings.mask_token"),
    (r"^pretrained\.pos_embed$", "backbone.embeddings.position_embeddings"),
    (r"^pretrained\.patch_embed\.proj\.", "backbone.embeddings.patch_embeddings.projection."),
    (
        r"^pretrained\.blocks\.(\d+)\.ls(\d)\.gamma$",
        r"backbone.encoder.layer.\1.layer_scale\2.lambda1",
    ),
    (
        r"^pretrained\.blocks\.(\d+)\.attn\.proj\.",
        r"backbone.encoder.layer.\1.attention.output.dense.",
    ),
    (r"^pretrained\.blocks\.(\d+)\.", r"backbone.encoder.layer.\1."),
    (r"^pretrained\.norm\.", "backbone.layernorm."),
    (r"^depth_head\.projects\.(\d)\.", r"neck.reassemble_stage.layers.\1.projection."),
    (r"^depth_head\.resize_layers\.(\d)\.", r"neck.reassemble_stage.layers.\1.resize."),
    (r"^depth_head\.scratch\.output_conv1\.", "head.conv1."),
    (r"^depth_head\.scratch\.output_conv2\.0\.", "head.conv2."),
    (r"^depth_head\.scratch\.output_conv2\.2\.", "head.conv3."),
)
_QKV = re.compile(r"^pretrained\.blocks\.(\d+)\.attn\.qkv\.(weight|bias)$")
_CONVS = re.compile(r"^depth_head\.scratch\.layer(\d)_rn\.weight$")
_REFINE = re.compile(r"^depth_head\.scratch\.refinenet(\d)\.(.*)$")
# transformers 5 keeps the legacy names on disk and these in memory
_IN_MEMORY = {
    ".attention.attention.query.": ".attention.q_proj.",
    ".attention.attention.key.": ".attention.k_proj.",
    ".attention.attention.value.": ".attention.v_proj.",
    ".attention.output.dense.": ".attention.o_proj.",
}


_CHUNK = 1 << 24  # bytes read at a time while hashing weights
# Digests computed in this process, by the weights' path and its files' identity (inode, size,
# modification and change times): a prior, its cache and its checkpoint record hash once.
_DIGESTS: dict[tuple, str] = {}


def _weight_files(path: Path) -> list[Path]:
    """A prior's files: ``path`` itself, or a folder's files in name order (hidden files and
    folders left out: a Hub download's ``.cache``)."""
    if path.is_file():
        return [path]
    return sorted(
        p
        for p in path.rglob("*")
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(path).parts)
    )


def weights_digest(weights: str | Path) -> str:
    """SHA-256 of a prior's weights: a file's bytes, or a folder's files (names and bytes, in
    name order; hidden files and folders left out). Hashed once per process while the files
    keep their inode, size and times (about 0.3 s per 100 MB).

    Returns:
        64 hex digits.

    Raises:
        ArgumentError: ``weights`` does not exist (naming ``weights``).
    """
    path = Path(weights).expanduser()
    if not path.exists():
        raise ArgumentError(
            f"{{weights}}={weights}: no such file or folder", "weights", owner=__name__
        )
    files = _weight_files(path)
    identity = []
    for file in files:
        stat = file.stat()
        identity.append((str(file), stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns))
    key = (str(path.resolve()), path.is_file(), tuple(identity))
    if key not in _DIGESTS:
        digest = hashlib.sha256()
        for file in files:
            if file != path:
                digest.update(file.relative_to(path).as_posix().encode() + b"\0")
            with file.open("rb") as f:
                while chunk := f.read(_CHUNK):
                    digest.update(chunk)
        _DIGESTS[key] = digest.hexdigest()
    return _DIGESTS[key]


def _network_size(
    height: int, width: int, short_side: int | None, multiple: int
) -> tuple[int, int]:
    """``height`` × ``width`` scaled so that its short side is ``short_side`` (None: as it
    is), each side then rounded to the nearest multiple of ``multiple`` (at least one)."""
    scale = 1.0 if short_side is None else short_side / min(height, width)
    return (
        max(multiple, round(height * scale / multiple) * multiple),
        max(multiple, round(width * scale / multiple) * multiple),
    )


def _transformers() -> Any:
    try:
        import transformers
    except ImportError as err:
        raise MissingDependencyError(
            "prior=depth_anything_v2 needs transformers, which is not installed: "
            'pip install -e ".[prior]" in a clone of fusion-depth'
        ) from err
    transformers.utils.logging.disable_progress_bar()  # its per-load bars, in every run's log
    return transformers


@contextlib.contextmanager
def _hub_offline() -> Iterator[None]:
    """Every download path of ``huggingface_hub`` (and so of transformers) off while the prior
    loads: its offline switch set, in the environment and in the module that read it at import,
    so that a request anything makes raises instead of reaching the network."""
    names = ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE")
    saved_env = {name: os.environ.get(name) for name in names}
    try:
        from huggingface_hub import constants
    except ImportError:  # pragma: no cover - transformers depends on it
        constants = None
    saved = getattr(constants, "HF_HUB_OFFLINE", None)
    os.environ.update(dict.fromkeys(names, "1"))
    if constants is not None:
        constants.HF_HUB_OFFLINE = True
    try:
        yield
    finally:
        if constants is not None:
            constants.HF_HUB_OFFLINE = saved
        for name, value in saved_env.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


# A Depth Anything config.json's keys that would have transformers fetch a backbone (its config
# or weights) from the Hub or timm by name, and the values that keep it local.
_HUB_KEYS = {
    "backbone": "null (the backbone is described by backbone_config)",
    "use_pretrained_backbone": "false (the folder's own weights are loaded)",
    "use_timm_backbone": "false (the backbone is transformers' DINOv2)",
}


def _check_local_config(folder: Path, weights: Any) -> None:
    """Refuse a ``config.json`` that names a backbone to fetch by name (:data:`_HUB_KEYS`, or a
    ``backbone_config`` that is not a mapping, e.g. a Hub id), at its top level or inside
    ``backbone_config``: transformers would look it up on the network.

    Raises:
        ArgumentError: naming the file and the key, and the value that keeps loading local.
    """
    file = folder / "config.json"
    try:
        config = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise _weights_error(weights, f"{file} is not readable JSON ({_problem(err)})") from None
    if not isinstance(config, dict):
        raise _weights_error(weights, f"{file} holds a {type(config).__name__}; expected a mapping")
    nested = config.get("backbone_config")
    for where, node in (("", config), ("backbone_config.", nested)):
        if not isinstance(node, dict):
            continue
        for key, allowed in _HUB_KEYS.items():
            if node.get(key) not in (None, False):
                raise _weights_error(
                    weights,
                    f"{file} sets {where}{key}={json.dumps(node[key])}, which has transformers "
                    f"fetch a backbone by name from the network; the prior is read from local "
                    f"files only: expected {where}{key}: {allowed}",
                )
    if nested is not None and not isinstance(nested, dict):
        raise _weights_error(
            weights,
            f"{file} sets backbone_config={json.dumps(nested)}, a name transformers would look "
            "up on the network; the prior is read from local files only: expected "
            "backbone_config to be the backbone's config (a mapping), as transformers saves it",
        )


def _problem(err: BaseException) -> str:
    """What ``err`` says is wrong, in one line (:func:`fusion_depth.data.cache.one_line`):
    ``load_state_dict``'s message opens with a heading ("Error(s) in loading state_dict for
    X:") and names the problem on the next line."""
    from fusion_depth.data.cache import one_line

    heading, _, rest = str(err).strip().partition("\n")
    return one_line(ValueError(rest) if heading.endswith(":") and rest.strip() else err, 200)


def _weights_error(weights: Any, problem: str, owner: Any = None) -> ArgumentError:
    return ArgumentError(
        f"{{weights}}={weights}: {problem}",
        "weights",
        owner=owner or f"{__name__}.DepthAnythingPrior",
    )


def _renamed(name: str) -> str | None:
    refine = _REFINE.match(name)
    if refine:  # refinenet1 is the last fusion layer: transformers numbers them the other way
        index, rest = 4 - int(refine.group(1)), refine.group(2)
        rest = re.sub(r"^out_conv\.", "projection.", rest)
        rest = re.sub(r"resConfUnit(\d)\.conv(\d)\.", r"residual_layer\1.convolution\2.", rest)
        return f"neck.fusion_stage.layers.{index}.{rest}"
    convs = _CONVS.match(name)
    if convs:
        return f"neck.convs.{int(convs.group(1)) - 1}.weight"
    for pattern, replacement in _RENAMES:
        if re.match(pattern, name):
            return re.sub(pattern, replacement, name)
    return None


def convert_official_state_dict(
    state: Mapping[str, torch.Tensor], weights: Any = "weights"
) -> dict[str, torch.Tensor]:
    """The authors' Depth Anything V2 state dict in transformers' on-disk names (the fused
    ``qkv`` projection split into query, key and value, in that order).

    Args:
        state: the ``.pth`` file's flat ``name → tensor`` mapping.
        weights: the file, for the error message.

    Raises:
        ArgumentError: a name the authors' model does not have (naming the first few).
    """
    converted, unknown = {}, []
    for name, tensor in state.items():
        qkv = _QKV.match(name)
        if qkv:
            prefix = f"backbone.encoder.layer.{qkv.group(1)}.attention.attention"
            for part, chunk in zip(("query", "key", "value"), tensor.chunk(3), strict=True):
                converted[f"{prefix}.{part}.{qkv.group(2)}"] = chunk
            continue
        new = _renamed(name)
        if new is None:
            unknown.append(name)
        else:
            converted[new] = tensor
    if unknown:
        raise _weights_error(
            weights,
            f"not a Depth Anything V2 checkpoint: unexpected keys {', '.join(unknown[:3])}"
            + (f" (and {len(unknown) - 3} more)" if len(unknown) > 3 else ""),
        )
    return converted


def depth_anything_config(state: Mapping[str, torch.Tensor], weights: Any = "weights") -> Any:
    """transformers' ``DepthAnythingConfig`` of a converted state dict, read from its shapes:
    embedding width, depth and training size from the backbone, neck, fusion and head widths
    from their convolutions; the blocks that feed the head from :data:`OUT_INDICES`.

    Raises:
        ArgumentError: a state dict that is not Depth Anything V2's (a missing tensor, a width
            that is not a multiple of 64, or a depth other than 12 or 24).
    """
    transformers = _transformers()
    try:
        width = state["backbone.embeddings.cls_token"].shape[-1]
        grid = round((state["backbone.embeddings.position_embeddings"].shape[1] - 1) ** 0.5)
        depth = 1 + max(
            int(name.split(".")[3]) for name in state if name.startswith("backbone.encoder.layer.")
        )
        necks = [
            state[f"neck.reassemble_stage.layers.{i}.projection.weight"].shape[0] for i in range(4)
        ]
        fusion = state["neck.convs.0.weight"].shape[0]
        head = state["head.conv2.weight"].shape[0]
    except (KeyError, ValueError) as err:
        raise _weights_error(weights, f"not a Depth Anything V2 checkpoint (no {err})") from None
    if width % HEAD_WIDTH or depth not in OUT_INDICES:
        raise _weights_error(
            weights,
            f"an encoder {width} wide and {depth} blocks deep; Depth Anything V2's are a multiple "
            f"of {HEAD_WIDTH} wide and {' or '.join(map(str, OUT_INDICES))} deep",
        )
    backbone = transformers.Dinov2Config(
        image_size=grid * PATCH,  # the authors' 518: 37 × 37 patches
        patch_size=PATCH,
        hidden_size=width,
        num_hidden_layers=depth,
        num_attention_heads=width // HEAD_WIDTH,
        out_indices=list(OUT_INDICES[depth]),
        apply_layernorm=True,
        reshape_hidden_states=False,
    )
    return transformers.DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=PATCH,
        reassemble_hidden_size=width,
        neck_hidden_sizes=necks,
        fusion_hidden_size=fusion,
        head_hidden_size=head,
        depth_estimation_type="relative",
    )


def _load_checkpoint_file(path: Path) -> nn.Module:
    """The authors' ``.pth``: tensors only (``weights_only``), mapped and loaded strictly."""
    transformers = _transformers()
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any failure means "not a readable checkpoint"
        problem = f"not a readable PyTorch checkpoint ({type(err).__name__})"
        raise _weights_error(path, problem) from None
    if not isinstance(state, Mapping) or not all(
        isinstance(v, torch.Tensor) for v in state.values()
    ):
        raise _weights_error(path, "expected a flat name → tensor state dict (the authors' .pth)")
    converted = convert_official_state_dict(state, path)
    model = transformers.DepthAnythingForDepthEstimation(depth_anything_config(converted, path))
    expected = model.state_dict()
    if not any(name in expected for name in converted if ".attention.attention." in name):
        for old, new in _IN_MEMORY.items():
            converted = {name.replace(old, new): value for name, value in converted.items()}
    try:
        model.load_state_dict(converted, strict=True)
    except RuntimeError as err:
        raise _weights_error(path, f"does not fit Depth Anything V2 ({_problem(err)})") from None
    return model


def load_depth_anything_v2(weights: str | Path) -> nn.Module:
    """Depth Anything V2 (relative) from local files: a transformers folder or the authors'
    ``.pth``. Nothing is downloaded, whatever the folder says: a ``config.json`` that names a
    backbone to fetch by name (``backbone``, ``use_pretrained_backbone``,
    ``use_timm_backbone``, a ``backbone_config`` that is a Hub id) is refused, and the folder is
    read with the Hub's offline switch on (``HF_HUB_OFFLINE``) and ``local_files_only``.

    Args:
        weights: the folder (with ``config.json``) or the ``.pth`` file.

    Returns:
        transformers' ``DepthAnythingForDepthEstimation``, in eval mode.

    Raises:
        ArgumentFileError: ``weights`` does not exist.
        ArgumentError: a folder without ``config.json``, with one that names a backbone to
            fetch (naming the file and key) or of another architecture, or a file that is not
            a Depth Anything V2 checkpoint, naming ``weights``.
        MissingDependencyError: transformers is not installed.
    """
    path = Path(weights).expanduser()
    if not path.exists():
        raise ArgumentFileError(
            f"{{weights}}={weights}: no such file or folder (expected a transformers folder, "
            "or the authors' depth_anything_v2_vit*.pth)",
            "weights",
            owner=DepthAnythingPrior,
        )
    if path.is_file():
        return _load_checkpoint_file(path).eval()
    transformers = _transformers()
    if not (path / "config.json").is_file():
        problem = "a folder without config.json (expected a transformers folder)"
        raise _weights_error(weights, problem)
    _check_local_config(path, weights)
    with _hub_offline():
        try:
            config = transformers.AutoConfig.from_pretrained(path, local_files_only=True)
        except Exception as err:  # noqa: BLE001 - any failure means "not a readable config"
            problem = f"config.json is not readable ({type(err).__name__})"
            raise _weights_error(weights, problem) from None
        if config.model_type != "depth_anything":
            raise _weights_error(weights, f"a {config.model_type} model (expected depth_anything)")
        if getattr(config, "depth_estimation_type", "relative") != "relative":
            problem = (
                "a metric Depth Anything (expected a relative one, e.g. Depth-Anything-V2-Small)"
            )
            raise _weights_error(weights, problem)
        try:
            model, info = transformers.DepthAnythingForDepthEstimation.from_pretrained(
                path, config=config, local_files_only=True, output_loading_info=True
            )
        except Exception as err:  # noqa: BLE001 - missing or corrupt weights file
            raise _weights_error(weights, f"cannot be loaded ({_problem(err)})") from None
    missing = [*info.get("missing_keys", ()), *info.get("mismatched_keys", ())]
    if missing:
        raise _weights_error(weights, f"weights do not fit its config.json ({missing[0]})")
    return model.eval()


class DepthAnythingPrior(nn.Module):
    """A frozen Depth Anything V2: RGB in, relative inverse depth out, at the input's size.

    The image is normalised with ImageNet's mean and standard deviation, resized (bilinear) so
    that its short side is ``input_size`` and both sides are multiples of 14, and the output is
    resized back. The network stays in eval mode and takes no gradient.

    Args:
        weights: a transformers folder or the authors' ``.pth`` (:func:`load_depth_anything_v2`).
        input_size: the short side the network sees; None keeps the image's. Both sides are
            then rounded to the nearest multiple of 14, as the authors' processor does
            (``ensure_multiple_of=14``); they infer at 518.

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1].
        - output: (B, 1, H, W) relative inverse depth, ≥ 0 (larger is nearer; affine-invariant).

    Attributes:
        weights: the file or folder it was built from, as given.
        weights_sha256: :func:`weights_digest` of it, recorded with the checkpoints of a network
            that takes this prior (:data:`PRIOR_KEY`).

    Raises:
        ArgumentError: ``weights`` cannot be loaded (see :func:`load_depth_anything_v2`), or
            ``input_size`` is below 14.
    """

    def __init__(self, weights: str | Path, input_size: int | None = 518) -> None:
        super().__init__()
        if input_size is not None and input_size < PATCH:
            raise ArgumentError(
                f"{{input_size}}={input_size}: expected an integer ≥ {PATCH}, or null",
                "input_size",
                owner=DepthAnythingPrior,
            )
        self.network = load_depth_anything_v2(weights)
        self.network.requires_grad_(False)
        self.weights = str(weights)
        self.weights_sha256 = weights_digest(weights)  # what it was built from (PRIOR_KEY)
        self.input_size = input_size
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def train(self, mode: bool = True) -> DepthAnythingPrior:
        super().train(mode)
        self.network.eval()  # frozen: its dropout and norms stay in inference mode
        return self

    def network_size(self, height: int, width: int) -> tuple[int, int]:
        """The size the network sees for an image of ``height`` × ``width``."""
        return _network_size(height, width, self.input_size, PATCH)

    @torch.no_grad()
    def forward(self, image: torch.Tensor) -> torch.Tensor:
        height, width = image.shape[-2:]
        size = self.network_size(height, width)
        pixels = F.interpolate((image - self.mean) / self.std, size, mode="bilinear")
        relative = self.network(pixel_values=pixels).predicted_depth[:, None].float()
        return F.interpolate(relative, (height, width), mode="bilinear").clamp_min(0.0)


def _read_prior_checkpoint(path: Path, weights: Any) -> tuple[dict, dict[str, torch.Tensor]]:
    """The network config (``model.net``) and the network's weights of a checkpoint ``train``
    wrote, read weights-only, every part checked before it is used.

    Raises:
        ArgumentError: one line naming ``weights``: a file that is not a readable checkpoint,
            that holds no run config with a ``model.net`` mapping, or whose ``state_dict`` is
            not a mapping of names to tensors.
    """
    from fusion_depth.models._registry import network_state
    from fusion_depth.utils.checkpoint_file import CONFIG_KEY, read_checkpoint

    def refuse(problem: str) -> ArgumentError:
        return _weights_error(weights, problem, CheckpointPrior)

    try:  # read_checkpoint also checks the state_dict: names to tensors
        checkpoint = read_checkpoint(path)
    except CheckpointError as err:  # "ckpt_path=<file>: <problem>": this file is prior.weights
        raise refuse(_problem(ValueError(str(err).partition(": ")[2] or str(err)))) from None
    model = checkpoint[CONFIG_KEY].get("model")
    net_config = model.get("net") if isinstance(model, dict) else None
    if not isinstance(net_config, dict):
        raise refuse(
            f"its run config ({CONFIG_KEY}) names no network; expected a checkpoint written "
            "by fusion_depth.train"
        )
    return net_config, network_state(checkpoint["state_dict"])


class CheckpointPrior(nn.Module):
    """A network of this platform as a frozen prior (``prior=checkpoint``): the RGB network of a
    checkpoint ``train`` wrote, rebuilt by its name from the package's table, whose raw output
    (reciprocal depth) serves as the relative inverse depth. Trained with ``loss=ssi`` it is
    relative by construction, as a foundation model's is: the built-in dataset's stand-in for
    one, since no foundation weights can be downloaded here.

    Args:
        weights: the checkpoint (``fusion=rgb``: a prior sees the image alone).
        input_size: the short side the network sees; None keeps the image's. Both sides are
            then rounded to the nearest multiple of 32, as the encoders need.

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1].
        - output: (B, 1, H, W) relative inverse depth (a network trained with ``loss=ssi`` may
          give values below 0: only its affine shape is meaningful).

    Attributes:
        weights, weights_sha256: as :class:`DepthAnythingPrior`'s (the digest of the file).

    Raises:
        ArgumentFileError: ``weights`` does not exist.
        ArgumentError: not a checkpoint written by ``train`` (unreadable, no run config, or a
            ``state_dict`` that is not a mapping of names to tensors), a network that takes
            sparse input, or weights that do not fit the network its config names; one line
            naming ``weights``.
    """

    def __init__(self, weights: str | Path, input_size: int | None = None) -> None:
        super().__init__()
        from fusion_depth.models._registry import network_from_checkpoint

        path = Path(weights).expanduser()
        if not path.is_file():
            raise ArgumentFileError(
                f"{{weights}}={weights}: no such file (expected a checkpoint written by "
                "fusion_depth.train with fusion=rgb)",
                "weights",
                owner=CheckpointPrior,
            )
        net_config, state = _read_prior_checkpoint(path, weights)
        if net_config.get("fusion", "rgb") != "rgb":  # checked before anything is built
            raise _weights_error(
                weights,
                f"a network with fusion={net_config['fusion']}; a prior sees the image alone: "
                "expected a checkpoint trained with fusion=rgb",
                CheckpointPrior,
            )
        try:
            self.network = network_from_checkpoint(net_config)
            self.network.load_state_dict(state)
        except (ValueError, TypeError, RuntimeError) as err:
            problem = f"cannot be rebuilt ({_problem(err)})"
            raise _weights_error(weights, problem, CheckpointPrior) from None
        if self.network.output_space != "reciprocal":
            raise _weights_error(
                weights,
                f"model={net_config.get('name')} predicts metres; a prior is an inverse depth: "
                "expected a network that predicts reciprocal depth (model=densedepth)",
                CheckpointPrior,
            )
        self.network.eval().requires_grad_(False)
        self.input_size = input_size
        self.weights = str(weights)
        self.weights_sha256 = weights_digest(path)  # what it was built from (PRIOR_KEY)

    def train(self, mode: bool = True) -> CheckpointPrior:
        super().train(mode)
        self.network.eval()  # frozen: its batch norms keep their statistics
        return self

    @torch.no_grad()
    def forward(self, image: torch.Tensor) -> torch.Tensor:
        height, width = image.shape[-2:]
        size = _network_size(height, width, self.input_size, 32)
        resized = F.interpolate(image, size, mode="bilinear") if size != (height, width) else image
        relative = self.network(resized, None).float()
        return F.interpolate(relative, (height, width), mode="bilinear")


# The priors a network can take by name (``prior.name``): the class and the arguments it reads.
PRIORS: dict[str, type[nn.Module]] = {
    "depth_anything_v2": DepthAnythingPrior,
    "checkpoint": CheckpointPrior,
}
NO_PRIOR = "none"
# What a prior's arguments accept (fusion_depth.utils.schema); ``dropout`` is the network's share
# of training frames given none (DepthNet).
ARGUMENT_RULES: Schema = {
    "input_size": Rule(
        lambda v: v is None or (POSITIVE_INT.ok(v) and v >= PATCH),
        f"an integer ≥ {PATCH}, or null (the image's own size)",
    ),
    "dropout": PROBABILITY,
    "cache": BOOLEAN,  # the runner's: computed once per frame (fusion_depth.runner.prior_cache)
}


def build_prior(
    name: str = NO_PRIOR, weights: str | None = None, input_size: int | None = 518
) -> nn.Module | None:
    """The frozen prior ``name`` (a key of :data:`PRIORS`), or None for ``none``.

    Args:
        name: ``none`` or a key of :data:`PRIORS`.
        weights: its weights (see :class:`DepthAnythingPrior`).
        input_size: the short side the prior sees.

    Raises:
        ArgumentError: an unknown ``name``, or a prior that cannot be built from ``weights``.
    """
    if name == NO_PRIOR:
        return None
    check_choice(name, (NO_PRIOR, *PRIORS), "name", owner=build_prior)
    return PRIORS[name](weights, input_size=input_size)


def normalized_prior(relative: torch.Tensor) -> torch.Tensor:
    """A relative prior mapped to [0, 1] per frame (its minimum to 0, its maximum to 1): the
    prior is affine-invariant, so only its shape within the frame carries information.

    Shape:
        - relative: (B, 1, H, W).
        - output: (B, 1, H, W); a flat frame gives 0.
    """
    low = relative.amin(dim=(-2, -1), keepdim=True)
    span = relative.amax(dim=(-2, -1), keepdim=True) - low
    return torch.where(span > 0, (relative - low) / span.clamp_min(1e-12), 0.0)


def keep_prior_out_of_checkpoints(module: nn.Module) -> None:
    """Leave the weights of ``module.prior`` (a frozen prior built from its own files) out of
    ``module``'s state dict, and fill them in from that prior when a state dict is loaded: a
    checkpoint holds the network's weights and names the prior's file, not a copy of it."""
    module.register_state_dict_post_hook(_without_prior)
    module.register_load_state_dict_pre_hook(_with_own_prior)


def _without_prior(module: nn.Module, state: dict, prefix: str, metadata: Any) -> None:
    for key in [k for k in state if k.startswith(f"{prefix}prior.")]:
        del state[key]


def _with_own_prior(module: nn.Module, state: dict, prefix: str, *args: Any) -> None:
    for key, value in module.prior.state_dict().items():
        state.setdefault(f"{prefix}prior.{key}", value)


# The checkpoint entry that records which prior a network was trained with (written by
# fusion_depth.runner.module.DepthModule, checked wherever a checkpoint is loaded).
PRIOR_KEY = "fusion_depth_prior"


def prior_record(net: nn.Module) -> dict[str, str] | None:
    """What a checkpoint of ``net`` records of its prior: ``{"name", "weights", "sha256"}``
    (the prior's file or folder and :func:`weights_digest` of it, taken when the prior was
    built); None for a network without a prior built from files."""
    prior = getattr(net, "prior", None)
    digest = getattr(prior, "weights_sha256", None)
    if not isinstance(digest, str):
        return None
    name = next((n for n, cls in PRIORS.items() if type(prior) is cls), type(prior).__name__)
    return {"name": name, "weights": str(prior.weights), "sha256": digest}


def check_prior_record(net: nn.Module, record: Any, where: str) -> None:
    """Refuse to serve a checkpoint's network with another prior than it was trained with:
    ``record`` (the checkpoint's :data:`PRIOR_KEY`, :func:`prior_record`) against the prior
    ``net`` has just built from its files. A checkpoint written before digests were recorded
    (no ``record``) is served with a warning: nothing can be checked. Nothing is checked for a
    network served without its prior.

    Args:
        net: the rebuilt network (its ``prior`` built from the weights now on disk).
        record: what the checkpoint records, or None.
        where: the checkpoint, for messages (``ckpt_path=<file>``).

    Raises:
        CheckpointError: one line naming the prior's file and both digests (the one trained
            with, the one found), or a record that is not what :func:`prior_record` writes.
    """
    found = prior_record(net)
    if found is None:
        return
    if record is None:
        log.warning(
            "%s records no digest of its prior (written before they were recorded); cannot "
            "check that %s holds the prior it was trained with",
            where,
            found["weights"],
        )
        return
    if not isinstance(record, dict) or not isinstance(record.get("sha256"), str):
        raise CheckpointError(
            f"{where}: its {PRIOR_KEY} entry is {type(record).__name__} without a sha256 "
            "string; expected the mapping fusion_depth.train writes (name, weights, sha256)"
        )
    if record["sha256"] != found["sha256"]:
        trained = record.get("weights")
        trained = f" (from {trained})" if isinstance(trained, str) else ""
        raise CheckpointError(
            f"{where}: its network was trained with the prior of sha256 {record['sha256'][:16]}"
            f"{trained}, but {found['weights']} now holds sha256 {found['sha256'][:16]}; "
            "refused, as another prior gives the network inputs it was not trained on: give "
            f"prior={found['name']} prior.weights=<a copy of the weights it was trained with>, "
            "or train again"
        )
