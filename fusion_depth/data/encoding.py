"""A sample's two forms: encoded, as it crosses the DataLoader's process boundary, and float, as
models, losses and metrics see it.

The prepared caches and the built-in dataset store images as uint8 and depth maps as uint16 in
1/256 m (:data:`~fusion_depth.data.depth_io.DEPTH_PNG_SCALE`, KITTI's convention), so a loader
worker passes them on in that form (:class:`~fusion_depth.data.EncodedSample`, from a reader's
``encoded_sample(index)``): 7 bytes a pixel instead of the float form's 20, and no conversion in
the worker. :func:`decode_sample` turns them into float32 after the transfer, on the device.
It is the one conversion every consumer goes through:

* ``DepthModule.on_after_batch_transfer`` (every Lightning stage: training, validation, test,
  ``evaluate``), before the training augmentation;
* ``bench``'s data stage, before the augmentation it times;
* a reader's ``__getitem__``, on the CPU, for code that reads a dataset directly (``predict``'s
  ``split:`` input, :func:`~fusion_depth.runner.datamodule.check_scorable`, tests).

So every path sees the same floats, bit for bit: ``image / 255`` and ``depth / 256`` in float32
(the second exact: every uint16 / 256 is a float32), what the readers served before the encoded
form existed. Tensors already floating point pass through unchanged, so a custom reader that
serves the float form (:class:`~fusion_depth.data.Sample`) works as it is.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from fusion_depth.data import EncodedSample
from fusion_depth.data.depth_io import DEPTH_PNG_SCALE

IMAGE_SCALE = 255.0  # float image = uint8 image / IMAGE_SCALE, in [0, 1]
# The depth maps of a sample, in metres (depth_measured: a training split's measured ground
# truth beside its filled depth, for a loss that reads both; see IndexedDataset's serve_measured).
DEPTH_KEYS: tuple[str, ...] = ("sparse", "depth", "depth_measured")


def encode_sample(
    image: np.ndarray, sparse: np.ndarray, depth: np.ndarray, condition: str
) -> EncodedSample:
    """The encoded sample of one frame's stored arrays (they are not copied, except the image,
    which goes from rows of pixels to planes of channels).

    Args:
        image: uint8 (H, W, 3) RGB.
        sparse: uint16 (H, W), metres × :data:`~fusion_depth.data.depth_io.DEPTH_PNG_SCALE`,
            0 = no value; a writable array (a copy of a memory map, not the map).
        depth: the ground truth, uint16 (H, W), in the same encoding as ``sparse``.
        condition: the frame's condition.

    Raises:
        ValueError: an array of another dtype or shape, naming it.
    """
    for name, array, dtype, ndim in (
        ("image", image, np.uint8, 3),
        ("sparse", sparse, np.uint16, 2),
        ("depth", depth, np.uint16, 2),
    ):
        if array.dtype != dtype or array.ndim != ndim or array.shape[:2] != image.shape[:2]:
            raise ValueError(
                f"encode_sample: {name} is {array.dtype} {array.shape}, expected "
                f"{np.dtype(dtype)} of the image's size {image.shape[:2]}"
            )
    if image.shape[2] != 3:
        raise ValueError(f"encode_sample: image is {image.shape}, expected (H, W, 3)")
    return {
        "image": torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))),
        "sparse": torch.from_numpy(sparse)[None],
        "depth": torch.from_numpy(depth)[None],
        "condition": condition,
    }


def decode_sample(sample: Mapping[str, Any]) -> dict[str, Any]:
    """The float form (:class:`~fusion_depth.data.Sample`) of an encoded sample or batch, on the
    device its tensors are on; other keys are kept as they are.

    ``image``: uint8 (..., 3, H, W) to float32 / 255, in [0, 1]. ``sparse`` and ``depth``:
    uint16 (..., 1, H, W) to float32 metres (/ 256; 0 stays 0, no value). A floating-point
    tensor is taken as already decoded and passed through, so decoding twice changes nothing.

    Raises:
        ValueError: ``image`` of another integer dtype than uint8, or a depth map of another
            than uint16, naming the key and dtype (no scale is known for them).
    """
    out = dict(sample)
    scales = {"image": (torch.uint8, IMAGE_SCALE)}
    scales.update(dict.fromkeys(DEPTH_KEYS, (torch.uint16, DEPTH_PNG_SCALE)))
    for key, (dtype, scale) in scales.items():
        value = sample.get(key)
        if value is None or value.is_floating_point():
            continue
        if value.dtype != dtype:
            raise ValueError(
                f"sample[{key!r}] is {value.dtype}: expected {dtype} (encoded) or a floating "
                "point tensor (decoded)"
            )
        out[key] = value.float().div_(scale)
    return out
