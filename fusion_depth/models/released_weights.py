"""Reading a published method's released weights as its authors saved them: the one way both
:mod:`~fusion_depth.models.radarnet_released` and
:mod:`~fusion_depth.models.sparse_beats_dense_released` read their files and check them against
the network built here, so that a bad file is one line naming it and its first wrong key.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import torch
from torch import Tensor

from fusion_depth.errors import ArgumentError, ArgumentFileError
from fusion_depth.utils.checkpoint_file import CheckpointError, load_weights_only


class ReleasedWeightsError(ArgumentError, CheckpointError):
    """A file that is not a released network as built here: one line naming the file and the
    first key (or entry) that is missing, unexpected, not a tensor or of another shape."""


def released_error(
    path: object, message: str, argument: str, owner: object
) -> ReleasedWeightsError:
    """``{argument}={path}: {message}``, about ``owner``'s ``argument`` (the config layer names
    the key that set it)."""
    return ReleasedWeightsError(f"{{{argument}}}={path}: {message}", argument, owner=owner)


def read_released(
    path: str | os.PathLike,
    argument: str,
    owner: object,
    allowed_globals: Iterable[Any] = (),
) -> Any:
    """A released file's contents, read with ``torch.load(weights_only=True)``
    (:func:`~fusion_depth.utils.checkpoint_file.load_weights_only`), with only
    ``allowed_globals`` added to what it may rebuild (``torch.serialization.safe_globals``).

    Raises:
        ArgumentFileError: no file at ``path``.
        ReleasedWeightsError: a file that cannot be read with weights only.
    """
    try:
        with torch.serialization.safe_globals(list(allowed_globals)):
            return load_weights_only(path)
    except FileNotFoundError:
        raise ArgumentFileError(
            f"{{{argument}}}={path}: no such file", argument, owner=owner
        ) from None
    except CheckpointError as err:
        # load_weights_only names the file as ckpt_path=...; here it is this argument's.
        raise released_error(path, str(err).split(": ", 1)[-1], argument, owner) from None


def matched_state(
    stored: Mapping[Any, Any],
    expected: Mapping[str, Tensor],
    entry: str,
    fail: Callable[[str], Exception],
    prefix: str = "",
) -> dict[str, Tensor]:
    """The tensors of ``stored`` (one entry of a released file, named ``entry`` in messages)
    under the names of ``expected`` (a file key less ``prefix``: ``torch.nn.DataParallel``'s
    ``module.``), checked key by key and shape by shape: every key of ``expected`` is there,
    no other, each a tensor of its shape.

    Raises:
        Exception: what ``fail(message)`` returns, for the first key that is unexpected, not a
            tensor, of another shape or missing (named as in the file: ``entry['key']``).
    """
    state: dict[str, Tensor] = {}
    for key, value in stored.items():
        name, where = str(key).removeprefix(prefix), f"{entry}[{key!r}]"
        if name not in expected:
            raise fail(f"unexpected key {where}")
        if not isinstance(value, Tensor):
            raise fail(f"{where} is a {type(value).__name__}")
        if value.shape != expected[name].shape:
            raise fail(f"{where} is {list(value.shape)}, expected {list(expected[name].shape)}")
        state[name] = value
    for name in expected:
        if name not in state:
            raise fail(f"missing key {entry}[{prefix + name!r}]")
    return state
