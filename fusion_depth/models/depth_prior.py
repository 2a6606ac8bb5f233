"""Frozen monocular depth priors: networks that give, per frame, either a relative
(affine-invariant) inverse depth, which :mod:`fusion_depth.models.alignment` makes metric with the
frame's radar, or a metric depth in metres. Each prior module says which in its ``kind``
attribute (:data:`KINDS`).

:class:`DepthAnythingPrior` is Depth Anything V2 (Yang et al., NeurIPS 2024) as ``transformers``
builds it (``DepthAnythingForDepthEstimation``), with weights read from local files only, never
downloaded: a transformers folder (``config.json`` and ``model.safetensors``, as
``depth-anything/Depth-Anything-V2-Small-hf`` ships) or the authors' ``.pth`` checkpoint
(``depth_anything_v2_vits.pth``, ``_vitb``, ``_vitl``; metric: ``depth_anything_v2_metric_
{hypersim,vkitti}_vit{s,b,l}.pth``), whose names are mapped to transformers' as its conversion
script ``convert_depth_anything_to_hf.py`` does. A relative model's head ends in a ReLU; a metric
one's in a sigmoid times ``max_depth`` (metres: 20 for the authors' Hypersim (indoor) models, 80
for their Virtual KITTI 2 (outdoor) ones; ``metric_depth/depth_anything_v2/dpt.py`` and
``metric_depth/README.md`` of github.com/DepthAnything/Depth-Anything-V2). Neither activation has
weights, so the two kinds hold the same tensors: which one a file is comes from its
``config.json`` (a folder) or from the user and the file's name (a ``.pth``; see
:func:`depth_anything_kind`). Licences: the Small weights are Apache-2.0; Base and Large are
CC-BY-NC-4.0 (the authors' README).

``transformers`` is an optional extra (``pip install -e ".[prior]"`` in a clone), imported on
first use.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
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
from fusion_depth.utils.schema import (
    BOOLEAN,
    PROBABILITY,
    Rule,
    Schema,
    is_int,
    is_number,
    one_of,
)

log = logging.getLogger(__name__)

PATCH = 14  # DINOv2's patch: the prior's input is resized to a multiple of it
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
# Which blocks feed the head, by the encoder's depth: ViT-S and ViT-B have 12, ViT-L 24
# (the authors' ``intermediate_layer_idx``, 1-based as transformers counts them).
OUT_INDICES = {12: (3, 6, 9, 12), 24: (5, 12, 18, 24)}
HEAD_WIDTH = 64  # DINOv2's attention heads are 64 wide: heads = embedding width / 64
# What a prior outputs (its ``kind``): relative inverse depth (≥ 0, larger nearer, known up to an
# affine map) or depth in metres.
RELATIVE, METRIC = "relative", "metric"
KINDS = (RELATIVE, METRIC)
# input_size: auto: the image's own short side, but never more than the authors' 518
AUTO = "auto"
AUTO_SHORT_SIDE = 518
# The authors' metric checkpoints, depth_anything_v2_metric_<data>_vit?.pth, each trained to a
# range (metres) by its data: Hypersim (indoor) 20, Virtual KITTI 2 80 (metric_depth/README.md).
METRIC_RANGES = {"hypersim": 20.0, "vkitti": 80.0}
_METRIC_FILE = re.compile(r"metric", re.IGNORECASE)
_RELATIVE_FILE = re.compile(r"^depth_anything_v2_vit[sblg]\.pth$")  # the authors' relative names
_RANGE_FILE = re.compile(r"metric_(hypersim|vkitti)_", re.IGNORECASE)
MAX_DEPTH = Rule(lambda v: is_number(v) and math.isfinite(v) and v > 0, "a number of metres > 0")

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


def short_side(height: int, width: int, input_size: int | str | None) -> int:
    """The short side a prior's network sees for an image of ``height`` × ``width``, before it
    is made a multiple of the patch: ``input_size`` itself (an integer), the image's own short
    side (None), or ``auto``: the image's own short side, at most :data:`AUTO_SHORT_SIDE` (518,
    the authors' size), so a small frame is not upscaled into tokens that add no pixels and a
    large one costs what the authors' setting costs."""
    own = min(height, width)
    if input_size is None:
        return own
    if input_size == AUTO:
        return min(own, AUTO_SHORT_SIDE)
    return int(input_size)


def authors_network_size(
    height: int, width: int, target: int, multiple: int = PATCH
) -> tuple[int, int]:
    """The size the authors' preprocessing gives an image of ``height`` × ``width`` for an input
    size ``target``: ``Resize(width=target, height=target, keep_aspect_ratio=True,
    ensure_multiple_of=multiple, resize_method="lower_bound")`` of ``depth_anything_v2/util/
    transform.py`` (Depth-Anything-V2), as ``infer_image`` uses it. The image is scaled by the
    larger of ``target / height`` and ``target / width`` (its short side to ``target``), each
    side then rounded to the nearest multiple of ``multiple`` (half to even, as ``np.round``),
    or up to the next one where that falls below ``target``.

    transformers' processor (``DPTImageProcessor`` with ``keep_aspect_ratio=True``, the Hub's
    ``Depth-Anything-V2-*-hf`` settings) gives the same size wherever the short side's scale is
    the one nearer 1 (every image scaled down, e.g. 900 × 1600 → 518 × 924), but otherwise
    scales as little as possible, its long side to ``target``: 64 × 192 becomes 168 × 518 there
    and 518 × 1554 here.

    Returns:
        (height, width), multiples of ``multiple``, each ≥ ``target``.
    """

    def constrain(value: float) -> int:
        rounded = round(value / multiple) * multiple
        return rounded if rounded >= target else math.ceil(value / multiple) * multiple

    scale_height, scale_width = target / height, target / width
    if scale_width > scale_height:
        scale_height = scale_width
    else:
        scale_width = scale_height
    return constrain(scale_height * height), constrain(scale_width * width)


def _nearest_size(height: int, width: int, side: int, multiple: int) -> tuple[int, int]:
    """``height`` × ``width`` scaled so that its short side is ``side``, each side then rounded
    to the nearest multiple of ``multiple`` (at least one): :class:`CheckpointPrior`'s."""
    scale = side / min(height, width)
    return (
        max(multiple, round(height * scale / multiple) * multiple),
        max(multiple, round(width * scale / multiple) * multiple),
    )


def _check_input_size(input_size: Any, owner: Any) -> None:
    if not ARGUMENT_RULES["input_size"].ok(input_size):
        raise ArgumentError(
            f"{{input_size}}={input_size!r}: expected {ARGUMENT_RULES['input_size'].expected}",
            "input_size",
            owner=owner,
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


def _config_json(folder: Path, weights: Any) -> dict:
    """A transformers folder's ``config.json``, read as data (JSON, a mapping).

    Raises:
        ArgumentError: naming ``weights``: a folder without it, or one that is not a JSON
            mapping.
    """
    file = folder / "config.json"
    if not file.is_file():
        raise _weights_error(
            weights, "a folder without config.json (expected a transformers folder)"
        )
    try:
        config = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise _weights_error(weights, f"{file} is not readable JSON ({_problem(err)})") from None
    if not isinstance(config, dict):
        raise _weights_error(weights, f"{file} holds a {type(config).__name__}; expected a mapping")
    return config


def _check_local_config(folder: Path, weights: Any) -> None:
    """Refuse a ``config.json`` that names a backbone to fetch by name (:data:`_HUB_KEYS`, or a
    ``backbone_config`` that is not a mapping, e.g. a Hub id), at its top level or inside
    ``backbone_config``: transformers would look it up on the network.

    Raises:
        ArgumentError: naming the file and the key, and the value that keeps loading local.
    """
    file = folder / "config.json"
    config = _config_json(folder, weights)
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


def depth_anything_config(
    state: Mapping[str, torch.Tensor],
    weights: Any = "weights",
    kind: str = RELATIVE,
    max_depth: float | None = None,
) -> Any:
    """transformers' ``DepthAnythingConfig`` of a converted state dict, read from its shapes:
    embedding width, depth and training size from the backbone, neck, fusion and head widths
    from their convolutions; the blocks that feed the head from :data:`OUT_INDICES`. The head's
    kind is not in the shapes (its last activation has no weights) and is ``kind``'s, as
    :func:`depth_anything_kind` resolved it.

    Args:
        state: the converted state dict (:func:`convert_official_state_dict`).
        weights: the file, for the error message.
        kind: ``relative`` (a ReLU head) or ``metric`` (a sigmoid head times ``max_depth``).
        max_depth: a metric head's range, metres. transformers 5 types the config's
            ``max_depth`` an integer; a range that is not one is set on the head when the
            model is built (:func:`_set_range`) and the config keeps its default.

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
    ranges = {}
    if kind == METRIC and max_depth is not None and float(max_depth).is_integer():
        ranges = {"max_depth": int(max_depth)}  # 20 or 80, as the conversion script writes it
    return transformers.DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=PATCH,
        reassemble_hidden_size=width,
        neck_hidden_sizes=necks,
        fusion_hidden_size=fusion,
        head_hidden_size=head,
        depth_estimation_type=kind,
        **ranges,
    )


def _set_range(model: nn.Module, kind: str, max_depth: float | None) -> nn.Module:
    """Set the head's ``max_depth`` (what its output is multiplied by) to a metric model's range;
    a relative head whose config holds none (``"max_depth": null``, which transformers 5
    multiplies by) to 1: its output is known only up to scale."""
    if kind == METRIC:
        model.head.max_depth = float(max_depth)
    elif model.head.max_depth is None:
        model.head.max_depth = 1.0
    return model


def _check_kind_arguments(kind: Any, max_depth: Any, owner: Any) -> None:
    check_choice(kind, (None, *KINDS), "kind", owner=owner)
    if max_depth is not None and not MAX_DEPTH.ok(max_depth):
        raise ArgumentError(
            f"{{max_depth}}={max_depth!r}: expected {MAX_DEPTH.expected}, or null",
            "max_depth",
            owner=owner,
        )


def _no_range(kind: str, max_depth: Any, owner: Any) -> tuple[str, None]:
    """A relative prior, refused with a ``max_depth``: it has no depth range."""
    if max_depth is not None:
        raise ArgumentError(
            f"{{max_depth}}={max_depth}: a relative prior ({{kind}}={kind}) outputs inverse "
            "depth up to an affine map and has no depth range; expected null",
            "max_depth",
            "kind",
            owner=owner,
        )
    return RELATIVE, None


def _range_hint(name: str) -> str:
    data = _RANGE_FILE.search(name)
    if data is not None:
        which = data.group(1).lower()
        metres = f"{METRIC_RANGES[which]:g}"
        return f"{metres} ({which}: the authors trained it to {metres} m)"
    return (
        "the metres its head was trained to (the authors': 20 for hypersim, indoor; 80 for "
        "vkitti, outdoor)"
    )


def _folder_kind(
    path: Path, weights: Any, kind: str | None, max_depth: float | None, owner: Any
) -> tuple[str, float | None]:
    """:func:`depth_anything_kind` of a transformers folder: its ``config.json`` decides."""
    config, file = _config_json(path, weights), path / "config.json"
    found = config.get("depth_estimation_type", RELATIVE)
    if found not in KINDS:
        problem = (
            f"{file} sets depth_estimation_type={json.dumps(found)}; expected one of {list(KINDS)}"
        )
        raise _weights_error(weights, problem)
    if kind is not None and kind != found:
        raise ArgumentError(
            f"{{kind}}={kind}: {file} sets depth_estimation_type={json.dumps(found)}, a "
            f"{found} Depth Anything ({_OUTPUTS[found]}); expected {{kind}}={found}, or null "
            "(read from config.json)",
            "kind",
            owner=owner,
        )
    if found == RELATIVE:
        return _no_range(RELATIVE, max_depth, owner)
    recorded = config.get("max_depth")
    if recorded is None:
        if max_depth is None:
            raise ArgumentError(
                f"{{max_depth}}=null: {file} sets no max_depth for its metric head (sigmoid × "
                f"max_depth); expected {_range_hint('')}",
                "max_depth",
                owner=owner,
            )
        return METRIC, float(max_depth)
    if not MAX_DEPTH.ok(recorded):
        problem = f"{file} sets max_depth={json.dumps(recorded)}; expected {MAX_DEPTH.expected}"
        raise _weights_error(weights, problem)
    if max_depth is not None and float(max_depth) != float(recorded):
        raise ArgumentError(
            f"{{max_depth}}={max_depth}: {file} sets max_depth={recorded}, the range its "
            f"metric head was trained to; expected null (read from config.json) or {recorded}",
            "max_depth",
            owner=owner,
        )
    return METRIC, float(recorded)


def depth_anything_kind(
    weights: str | Path, kind: str | None = None, max_depth: float | None = None
) -> tuple[str, float | None]:
    """Whether the Depth Anything V2 at ``weights`` is relative or metric, and a metric one's
    range, from what tells them apart. The two kinds hold the same tensors (the head's last
    activation, a ReLU or a sigmoid, has no weights; ``metric_depth/depth_anything_v2/dpt.py``
    multiplies the sigmoid by ``max_depth``), so neither the names nor the shapes of the weights
    can say which one a file is:

    * a transformers folder: its ``config.json``'s ``depth_estimation_type`` (``relative``
      where absent) and ``max_depth``. ``kind`` and ``max_depth`` may be left null; given, they
      must agree with it. A metric folder whose ``config.json`` sets no ``max_depth`` takes
      ``max_depth``.
    * the authors' ``.pth``: ``kind`` says (null: relative), and a metric one needs
      ``max_depth``. Where the file's name says which one it is, they must agree with it: a
      name holding ``metric`` (``depth_anything_v2_metric_vkitti_vits.pth``) is metric, the
      authors' relative names (``depth_anything_v2_vit{s,b,l,g}.pth``) relative, and the
      authors' metric names give their range (``hypersim``: 20 m, ``vkitti``: 80 m;
      ``metric_depth/README.md``). A ``.pth`` named neither way is what ``kind`` says.

    Args:
        weights: the folder or ``.pth`` file.
        kind: ``relative``, ``metric``, or None (from the folder's ``config.json``; a ``.pth``:
            relative).
        max_depth: a metric prior's range, metres (> 0); None: from ``config.json``.

    Returns:
        ``(kind, max_depth)``: ``("relative", None)`` or ``("metric", metres)``.

    Raises:
        ArgumentFileError: ``weights`` does not exist.
        ArgumentError: one line naming ``kind`` or ``max_depth`` and the file where they
            disagree with it, or a metric prior without a range; naming ``weights`` where its
            ``config.json`` cannot be read or sets an unknown kind.
    """
    owner = DepthAnythingPrior
    _check_kind_arguments(kind, max_depth, owner)
    path = Path(weights).expanduser()
    if not path.exists():
        raise ArgumentFileError(
            f"{{weights}}={weights}: no such file or folder (expected a transformers folder, "
            "or the authors' depth_anything_v2_vit*.pth)",
            "weights",
            owner=owner,
        )
    if path.is_dir():
        return _folder_kind(path, weights, kind, max_depth, owner)
    named = METRIC if _METRIC_FILE.search(path.name) else None
    named = RELATIVE if _RELATIVE_FILE.match(path.name) else named
    if named == METRIC and kind != METRIC:
        raise ArgumentError(
            f"{{kind}}={kind or 'null'}: {weights} is named as a metric checkpoint, whose head "
            "ends in a sigmoid times max_depth where a relative one's ends in a ReLU; no weights "
            "tell them apart, and read as relative its metres would be taken for inverse depth: "
            f"expected {{kind}}=metric {{max_depth}}={_range_hint(path.name)}",
            "kind",
            "max_depth",
            owner=owner,
        )
    if named == RELATIVE and kind == METRIC:
        raise ArgumentError(
            f"{{kind}}=metric: {weights} is named as the authors' relative checkpoint "
            "(depth_anything_v2_vit?.pth; their metric ones are depth_anything_v2_metric_"
            "<hypersim|vkitti>_vit?.pth); expected {kind}=relative, or null",
            "kind",
            owner=owner,
        )
    if kind != METRIC:
        return _no_range(RELATIVE, max_depth, owner)
    data = _RANGE_FILE.search(path.name)
    expected = METRIC_RANGES[data.group(1).lower()] if data else None
    if max_depth is None or (expected is not None and float(max_depth) != expected):
        shown = "null" if max_depth is None else max_depth
        raise ArgumentError(
            f"{{max_depth}}={shown}: {weights} is a metric .pth, which records no range: "
            f"expected {{max_depth}}={_range_hint(path.name)}",
            "max_depth",
            owner=owner,
        )
    return METRIC, float(max_depth)


_OUTPUTS = {
    RELATIVE: "relative inverse depth, larger nearer",
    METRIC: "depth in metres, sigmoid × max_depth",
}


def _load_checkpoint_file(
    path: Path, kind: str = RELATIVE, max_depth: float | None = None
) -> nn.Module:
    """The authors' ``.pth``: tensors only (``weights_only``), mapped and loaded strictly, with
    the head of ``kind`` (:func:`depth_anything_kind`)."""
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
    config = depth_anything_config(converted, path, kind, max_depth)
    model = transformers.DepthAnythingForDepthEstimation(config)
    expected = model.state_dict()
    if not any(name in expected for name in converted if ".attention.attention." in name):
        for old, new in _IN_MEMORY.items():
            converted = {name.replace(old, new): value for name, value in converted.items()}
    try:
        model.load_state_dict(converted, strict=True)
    except RuntimeError as err:
        raise _weights_error(path, f"does not fit Depth Anything V2 ({_problem(err)})") from None
    return _set_range(model, kind, max_depth)


def load_depth_anything_v2(
    weights: str | Path, kind: str | None = None, max_depth: float | None = None
) -> nn.Module:
    """Depth Anything V2, relative or metric, from local files: a transformers folder or the
    authors' ``.pth``. Nothing is downloaded, whatever the folder says: a ``config.json`` that
    names a backbone to fetch by name (``backbone``, ``use_pretrained_backbone``,
    ``use_timm_backbone``, a ``backbone_config`` that is a Hub id) is refused, and the folder is
    read with the Hub's offline switch on (``HF_HUB_OFFLINE``) and ``local_files_only``.

    Args:
        weights: the folder (with ``config.json``) or the ``.pth`` file.
        kind: which head it has, ``relative`` or ``metric`` (:func:`depth_anything_kind`: from
            the folder's ``config.json`` where None).
        max_depth: a metric head's range, metres (from ``config.json`` where None).

    Returns:
        transformers' ``DepthAnythingForDepthEstimation``, in eval mode: ``predicted_depth``
        (B, h, w) is relative inverse depth (≥ 0), or depth in metres in [0, max_depth].

    Raises:
        ArgumentFileError: ``weights`` does not exist.
        ArgumentError: a folder without ``config.json``, with one that names a backbone to
            fetch (naming the file and key) or of another architecture, or a file that is not
            a Depth Anything V2 checkpoint, naming ``weights``; a ``kind`` or ``max_depth``
            that disagrees with the weights (:func:`depth_anything_kind`).
        MissingDependencyError: transformers is not installed.
    """
    kind, max_depth = depth_anything_kind(weights, kind, max_depth)
    path = Path(weights).expanduser()
    if path.is_file():
        return _load_checkpoint_file(path, kind, max_depth).eval()
    transformers = _transformers()
    _check_local_config(path, weights)
    with _hub_offline():
        try:
            config = transformers.AutoConfig.from_pretrained(path, local_files_only=True)
        except Exception as err:  # noqa: BLE001 - any failure means "not a readable config"
            problem = f"config.json is not readable ({type(err).__name__})"
            raise _weights_error(weights, problem) from None
        if config.model_type != "depth_anything":
            raise _weights_error(weights, f"a {config.model_type} model (expected depth_anything)")
        try:
            model, info = transformers.DepthAnythingForDepthEstimation.from_pretrained(
                path, config=config, local_files_only=True, output_loading_info=True
            )
        except Exception as err:  # noqa: BLE001 - missing or corrupt weights file
            raise _weights_error(weights, f"cannot be loaded ({_problem(err)})") from None
    missing = [*info.get("missing_keys", ()), *info.get("mismatched_keys", ())]
    if missing:
        raise _weights_error(weights, f"weights do not fit its config.json ({missing[0]})")
    return _set_range(model, kind, max_depth).eval()


class DepthAnythingPrior(nn.Module):
    """A frozen Depth Anything V2: RGB in; relative inverse depth, or depth in metres, out, at
    the input's size.

    Preprocessing is transformers' ``DPTImageProcessor`` with the Hub's Depth Anything V2
    settings (bicubic with antialiasing, then ImageNet's mean and standard deviation; matched to
    1e-4 by the tests) at the authors' size (:func:`authors_network_size`, ``lower_bound``: the
    short side to :func:`short_side` of ``input_size``, both sides multiples of 14). The output
    is resized back bilinearly with ``align_corners=True``, as the authors' ``infer_image``
    does (``depth_anything_v2/dpt.py``). The network stays in eval mode and takes no gradient.

    Args:
        weights: a transformers folder or the authors' ``.pth`` (:func:`load_depth_anything_v2`).
        input_size: the short side the network sees, before it is made a multiple of 14: an
            integer ≥ 14 (the authors infer at 518); None: the image's own; ``auto``: the
            image's own, at most 518 (a 64 × 192 frame is seen at 70 × 196, a 900 × 1600 one at
            518 × 924, as with 518).
        kind: ``relative``, ``metric``, or None: read from a folder's ``config.json``; a
            ``.pth`` holds no kind and is relative unless told (:func:`depth_anything_kind`).
        max_depth: a metric prior's range, metres (the sigmoid's scale: 20 for the authors'
            Hypersim models, 80 for their Virtual KITTI 2 ones); None: from ``config.json``. A
            metric ``.pth`` needs it.

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1].
        - output: (B, 1, H, W): ``kind`` relative: relative inverse depth, ≥ 0 (larger is
          nearer; affine-invariant). ``kind`` metric: depth in metres, in [0, max_depth] (the
          sigmoid's (0, 1) times ``max_depth``).

    Attributes:
        kind: ``relative`` or ``metric`` (resolved: never None).
        max_depth: a metric prior's range, metres; None for a relative one.
        weights: the file or folder it was built from, as given.
        weights_sha256: :func:`weights_digest` of it, recorded with the checkpoints of a network
            that takes this prior (:data:`PRIOR_KEY`).

    Raises:
        ArgumentError: ``weights`` cannot be loaded (see :func:`load_depth_anything_v2`),
            ``kind`` or ``max_depth`` disagree with it (:func:`depth_anything_kind`), or
            ``input_size`` is not an integer ≥ 14, null or ``auto``.
    """

    def __init__(
        self,
        weights: str | Path,
        input_size: int | str | None = 518,
        kind: str | None = None,
        max_depth: float | None = None,
    ) -> None:
        super().__init__()
        _check_input_size(input_size, DepthAnythingPrior)
        self.kind, self.max_depth = depth_anything_kind(weights, kind, max_depth)
        self.network = load_depth_anything_v2(weights, self.kind, self.max_depth)
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
        """The size the network sees for an image of ``height`` × ``width``
        (:func:`authors_network_size` of :func:`short_side`)."""
        return authors_network_size(height, width, short_side(height, width, self.input_size))

    def preprocess(self, image: torch.Tensor) -> torch.Tensor:
        """The network's input: ``image`` resized to :meth:`network_size` (bicubic with
        antialiasing, ``align_corners=False``: torchvision's resize, which ``DPTImageProcessor``
        uses), then normalised with ImageNet's mean and standard deviation, in that order (the
        processor resizes, then rescales and normalises; the authors' ``Resize``, then
        ``NormalizeImage``).

        Shape:
            - image: (B, 3, H, W) RGB in [0, 1].
            - output: (B, 3, h, w), (h, w) = :meth:`network_size` (H, W).
        """
        size = self.network_size(*image.shape[-2:])
        if size != tuple(image.shape[-2:]):
            image = F.interpolate(image, size, mode="bicubic", antialias=True, align_corners=False)
        return (image - self.mean) / self.std

    @torch.no_grad()
    def forward(self, image: torch.Tensor) -> torch.Tensor:
        height, width = image.shape[-2:]
        out = self.network(pixel_values=self.preprocess(image)).predicted_depth[:, None].float()
        out = F.interpolate(out, (height, width), mode="bilinear", align_corners=True)
        # the head's range: ReLU's [0, ∞) or the sigmoid's [0, max_depth], which interpolating in
        # float32 may pass by a rounding error
        return out.clamp_min(0.0) if self.kind == RELATIVE else out.clamp(0.0, self.max_depth)


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
        input_size: the short side the network sees (:func:`short_side`): an integer, None
            (the image's), or ``auto`` (the image's, at most 518). Both sides are then rounded
            to the nearest multiple of 32, as the encoders need.
        kind: ``relative`` or None: this prior is relative (``metric`` is refused).
        max_depth: None (a relative prior has no range).

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1].
        - output: (B, 1, H, W) relative inverse depth (a network trained with ``loss=ssi`` may
          give values below 0: only its affine shape is meaningful).

    Attributes:
        kind: ``relative``; max_depth: None.
        weights, weights_sha256: as :class:`DepthAnythingPrior`'s (the digest of the file).

    Raises:
        ArgumentFileError: ``weights`` does not exist.
        ArgumentError: not a checkpoint written by ``train`` (unreadable, no run config, or a
            ``state_dict`` that is not a mapping of names to tensors), a network that takes
            sparse input, or weights that do not fit the network its config names; one line
            naming ``weights``. ``kind`` metric or a ``max_depth``, naming them.
    """

    def __init__(
        self,
        weights: str | Path,
        input_size: int | str | None = None,
        kind: str | None = None,
        max_depth: float | None = None,
    ) -> None:
        super().__init__()
        _check_input_size(input_size, CheckpointPrior)
        self.kind, self.max_depth = checkpoint_kind(weights, kind, max_depth)
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
        size = _nearest_size(height, width, short_side(height, width, self.input_size), 32)
        resized = F.interpolate(image, size, mode="bilinear") if size != (height, width) else image
        relative = self.network(resized, None).float()
        return F.interpolate(relative, (height, width), mode="bilinear")


def checkpoint_kind(
    weights: Any = None, kind: str | None = None, max_depth: float | None = None
) -> tuple[str, None]:
    """What :class:`CheckpointPrior` outputs: relative inverse depth, whatever its file, so
    ``("relative", None)``; ``kind`` metric or a ``max_depth`` is refused in one line."""
    _check_kind_arguments(kind, max_depth, CheckpointPrior)
    if kind == METRIC:
        raise ArgumentError(
            "{kind}=metric: prior=checkpoint is relative (a network's reciprocal depth, "
            "known up to an affine map); expected {kind}=relative, or null",
            "kind",
            owner=CheckpointPrior,
        )
    return _no_range(RELATIVE, max_depth, CheckpointPrior)


class ZeroPrior(nn.Module):
    """``prior=zero``: a prior that is 0 everywhere, read from no file: the control of a study
    of a prior as an input (``model=densedepth prior=zero``), whose network has the prior's
    branch and parameters but gets nothing through them. A gain over it is the prior's, not
    the branch's.

    Args:
        weights: ignored (must be null in the config: there is nothing to read).
        input_size: ignored.
        kind: ``relative`` or null.
        max_depth: null.

    Shape:
        - image: (B, 3, H, W); output: (B, 1, H, W) zeros.
    """

    kind = RELATIVE
    max_depth = None

    def __init__(
        self,
        weights: Any = None,
        input_size: Any = None,
        kind: str | None = None,
        max_depth: float | None = None,
    ) -> None:
        super().__init__()
        zero_kind(weights, kind, max_depth)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return image.new_zeros((image.shape[0], 1, *image.shape[2:]))


def zero_kind(
    weights: Any = None, kind: str | None = None, max_depth: float | None = None
) -> tuple[str, None]:
    """What :class:`ZeroPrior` outputs: ``("relative", None)``; weights, ``kind`` metric or a
    ``max_depth`` refused in one line."""
    _check_kind_arguments(kind, max_depth, ZeroPrior)
    if weights is not None:
        raise ArgumentError(
            f"{{weights}}={weights}: prior=zero reads no file; expected null",
            "weights",
            owner=ZeroPrior,
        )
    if kind == METRIC:
        raise ArgumentError(
            "{kind}=metric: prior=zero is no depth at all; expected null", "kind", owner=ZeroPrior
        )
    return _no_range(RELATIVE, max_depth, ZeroPrior)


# The oracle prior's form: an exact relative prior with a shift, as Depth Anything's output is.
ORACLE_SCALE, ORACLE_SHIFT = 3.0, 0.2


class OraclePrior(ZeroPrior):
    """``prior=oracle``: each frame's own ground truth made a perfect relative prior, ``3 /
    depth + 0.2`` (0.2 where the ground truth has no depth: the sky, infinitely far), for
    ``evaluate prior=oracle`` with no checkpoint: the global alignment of a prior that is
    exact up to its scale and shift, which measures the fit (its radar, its outliers) and
    nothing of a network. Only for datasets whose ground truth is dense (the built-in one).
    ``evaluate`` gives it frame by frame
    (:class:`~fusion_depth.evaluate.scoring.OracleAsPrior`); it cannot run on an image.

    Raises:
        ValueError: when run on an image (there is no ground truth in it).
    """

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        raise ValueError(
            "prior=oracle is each frame's ground truth: only evaluate with no ckpt_path gives "
            "it (the global alignment of a perfect prior); it cannot run on an image"
        )


def oracle_prior(depth: torch.Tensor) -> torch.Tensor:
    """:class:`OraclePrior`'s value for a ground truth ``depth`` in metres (0 = none): ``3 /
    depth + 0.2``, and 0.2 where there is none. Shape kept; float32."""
    depth = depth.float()
    inverse = torch.where(depth > 0, 1.0 / depth.clamp_min(1e-6), 0.0)
    return ORACLE_SCALE * inverse + ORACLE_SHIFT


# The priors a network can take by name (``prior.name``): the class and the arguments it reads.
PRIORS: dict[str, type[nn.Module]] = {
    "depth_anything_v2": DepthAnythingPrior,
    "checkpoint": CheckpointPrior,
    "zero": ZeroPrior,
    "oracle": OraclePrior,
}
# What each one outputs, from its settings alone (nothing built): (kind, max_depth).
_KIND_OF = {
    "depth_anything_v2": depth_anything_kind,
    "checkpoint": checkpoint_kind,
    "zero": zero_kind,
    "oracle": zero_kind,
}
NO_PRIOR = "none"
# What a prior's arguments accept (fusion_depth.utils.schema); ``dropout`` is the network's share
# of training frames given none (DepthNet).
ARGUMENT_RULES: Schema = {
    "input_size": Rule(
        lambda v: v is None or v == AUTO or (is_int(v) and v >= PATCH),
        f"an integer ≥ {PATCH}, null (the image's own size) or {AUTO} (the image's own, at "
        f"most {AUTO_SHORT_SIDE})",
    ),
    "kind": one_of(None, *KINDS),  # null: from the weights (a folder's config.json)
    "max_depth": MAX_DEPTH.or_null("from the weights' config.json; a relative prior's"),
    "dropout": PROBABILITY,
    "cache": BOOLEAN,  # the runner's: computed once per frame (fusion_depth.runner.prior_cache)
}


def build_prior(
    name: str = NO_PRIOR,
    weights: str | None = None,
    input_size: int | str | None = 518,
    kind: str | None = None,
    max_depth: float | None = None,
) -> nn.Module | None:
    """The frozen prior ``name`` (a key of :data:`PRIORS`), or None for ``none``: the ``prior``
    config node's keys, less the runner's (``dropout``, ``cache``).

    Args:
        name: ``none`` or a key of :data:`PRIORS`.
        weights: its weights (see :class:`DepthAnythingPrior`).
        input_size: the short side the prior sees (:func:`short_side`).
        kind: ``relative``, ``metric`` or None (from the weights: :func:`resolve_prior_kind`).
        max_depth: a metric prior's range, metres; None: from the weights.

    Returns:
        The prior module, whose ``kind`` attribute says what it outputs: ``relative`` (inverse
        depth up to an affine map) or ``metric`` (metres); None for ``none``.

    Raises:
        ArgumentError: an unknown ``name``, or a prior that cannot be built from ``weights``
            with these settings.
    """
    if name == NO_PRIOR:
        return None
    check_choice(name, (NO_PRIOR, *PRIORS), "name", owner=build_prior)
    return PRIORS[name](weights, input_size=input_size, kind=kind, max_depth=max_depth)


def resolve_prior_kind(
    name: str, weights: Any, kind: str | None = None, max_depth: float | None = None
) -> tuple[str, float | None]:
    """What the prior :func:`build_prior` builds from these settings outputs, read without
    building it: ``("relative", None)`` or ``("metric", max_depth in metres)``
    (:func:`depth_anything_kind`, :func:`checkpoint_kind`).

    Raises:
        ArgumentError: an unknown ``name`` (``none`` included: no prior, no kind), or settings
            that disagree with the weights (as :func:`build_prior` would).
    """
    check_choice(name, tuple(_KIND_OF), "name", owner=build_prior)
    return _KIND_OF[name](weights, kind, max_depth)


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


def prior_record(net: nn.Module) -> dict[str, Any] | None:
    """What a checkpoint of ``net`` records of its prior: ``{"name", "weights", "sha256",
    "kind", "max_depth"}`` (the prior's file or folder, :func:`weights_digest` of it, taken
    when the prior was built, and what it outputs: the same ``.pth`` may be read as relative or
    metric); None for a network without a prior built from files."""
    prior = getattr(net, "prior", None)
    digest = getattr(prior, "weights_sha256", None)
    if not isinstance(digest, str):
        return None
    name = next((n for n, cls in PRIORS.items() if type(prior) is cls), type(prior).__name__)
    kind = getattr(prior, "kind", RELATIVE)
    max_depth = getattr(prior, "max_depth", None)
    return {
        "name": name,
        "weights": str(prior.weights),
        "sha256": digest,
        "kind": kind,
        "max_depth": max_depth,
    }


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
            with, the one found), or its kind and range trained with and now (a ``.pth`` read
            as relative then, metric now), or a record that is not what :func:`prior_record`
            writes.
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
    # Records written before the kind was recorded hold a relative prior (metric was refused).
    trained = (record.get("kind", RELATIVE), record.get("max_depth"))
    if trained != (found["kind"], found["max_depth"]):
        raise CheckpointError(
            f"{where}: its network was trained with {found['weights']} read as "
            f"{_reading(*trained)}, but it is now read as "
            f"{_reading(found['kind'], found['max_depth'])}; refused, as the network would take "
            f"another kind or scale of depth than it learnt: give {_reading(*trained, 'prior.')}"
        )


def _reading(kind: Any, max_depth: Any, prefix: str = "") -> str:
    """``kind=metric max_depth=80`` (``prefix`` before each key)."""
    shown = f"{max_depth:g}" if is_number(max_depth) else max_depth
    return f"{prefix}kind={kind}" + (f" {prefix}max_depth={shown}" if max_depth is not None else "")
