"""Reading a checkpoint file without executing code from it (rebuilding a model from what it
records is :mod:`fusion_depth.runner.checkpoints`).

Checkpoints are read with ``torch.load(weights_only=True)``, which only rebuilds tensors and
plain containers. Training stores its run config in every checkpoint (``fusion_depth_config``)
as plain data, without Hydra's instantiation keys (:func:`plain_config`). A checkpoint that has
one anywhere (``_target_``, ``_partial_``, ...) is refused before anything else is done with it.
"""

from __future__ import annotations

import _compat_pickle  # pickle's own Python 2 → 3 name table
import os
import pickle
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from fusion_depth.errors import UserError

CONFIG_KEY = "fusion_depth_config"


RUN_KEY = "fusion_depth_run"


# Hydra's instantiation keys: a config holding one names code to import and call.
INSTANTIATION_KEYS = ("_target_", "_partial_", "_args_", "_recursive_", "_convert_")


_PLAIN_TYPES = (str, int, float, bool, type(None))


class CheckpointError(ValueError, UserError):
    """A checkpoint that cannot be used as asked; the message names the file and the problem
    (Hydra prints it alone, without a traceback)."""


def plain_config(config: Any) -> Any:
    """``config`` (a resolved run config: dicts, lists, scalars) without Hydra's instantiation
    keys, as training stores it in checkpoints: what a run was, never what code to call."""
    if isinstance(config, dict):
        return {k: plain_config(v) for k, v in config.items() if k not in INSTANTIATION_KEYS}
    if isinstance(config, list | tuple):
        return [plain_config(v) for v in config]
    return config


def _code_in(data: Any, where: str) -> Iterator[str]:
    """What in ``data`` would make Hydra or OmegaConf run code, each with its key path: an
    instantiation key (``a.b._target_``) or an interpolation string (``${oc.env:...}``, which
    runs a resolver when a config is built from it)."""
    if isinstance(data, dict):
        for key, value in data.items():
            path = f"{where}.{key}" if where else str(key)
            if key in INSTANTIATION_KEYS:
                yield f"the instantiation key {path}"
            yield from _code_in(value, path)
    elif isinstance(data, list | tuple):
        for i, value in enumerate(data):
            yield from _code_in(value, f"{where}[{i}]")
    elif isinstance(data, str) and "${" in data:
        yield f"an interpolation at {where} ({data[:60]!r})"


def check_no_code(
    checkpoint: Any,
    path: Path,
    key: str = "ckpt_path",
    what: str = "a checkpoint",
    writer: str = "fusion_depth.train",
) -> None:
    """Refuse a checkpoint that holds an instantiation key or an interpolation anywhere in it,
    naming the key path: a checkpoint is data, and the code it runs with is chosen by name from
    this package (training stores resolved configs without instantiation keys).

    Other files read as data are refused the same way: ``key`` names the option that gave
    ``path`` (empty: the message names the file alone), ``what`` the kind of file and
    ``writer`` the command that writes it."""
    where = f"{key}={path}" if key else str(path)
    try:
        found = next(_code_in(checkpoint, ""), None)
    except RecursionError:
        raise CheckpointError(f"{where}: refused; it is nested too deeply") from None
    if found is not None:
        raise CheckpointError(
            f"{where}: refused; it holds {found}, and {what} may only hold "
            f"plain data ({writer} writes neither)"
        )


def load_weights_only(
    path: str | os.PathLike, map_location: Any = "cpu", mmap: bool = False
) -> Any:
    """``torch.load(weights_only=True)`` of ``path``, with errors naming the file (``mmap``:
    tensors stay on disk until touched, for reading a checkpoint's small entries)."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path={path}: no such file")
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as err:
        # Named from the file itself, not from torch's wording (which changes between versions).
        objects = _unsafe_globals(path)
        if not objects:
            raise CheckpointError(f"ckpt_path={path}: not a readable PyTorch checkpoint") from err
        raise CheckpointError(
            f"ckpt_path={path}: refused to load; it holds a {', '.join(objects)} object, and "
            "weights-only loading never runs code from a file to rebuild objects"
        ) from err
    except Exception as err:  # noqa: BLE001 - bytes no checkpoint holds: any parse failure
        # (RuntimeError, EOFError, OSError; KeyError, ValueError, ... of a text file's bytes)
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        if isinstance(err, LookupError | ValueError | TypeError):
            reason = type(err).__name__  # KeyError: 101 says nothing to a user
        raise CheckpointError(
            f"ckpt_path={path}: not a readable PyTorch checkpoint ({reason})"
        ) from err
    check_no_code(checkpoint, path)
    return checkpoint


def _unsafe_globals(path: Path) -> list[str]:
    """The objects a checkpoint's pickle would have to import to be rebuilt (none if the file
    cannot even be parsed)."""
    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # noqa: BLE001 - any parse failure means "not a readable checkpoint"
        return []
    return [_python3_name(name) for name in names]


def _python3_name(name: str) -> str:
    """``module.name`` as Python 3 spells it: torch pickles with protocol 2, which stores some
    globals under their Python 2 names (``subprocess.Popen`` as ``commands.Popen``)."""
    module, _, attr = name.rpartition(".")
    if (module, attr) in _compat_pickle.NAME_MAPPING:
        module, attr = _compat_pickle.NAME_MAPPING[(module, attr)]
    else:
        module = _compat_pickle.IMPORT_MAPPING.get(module, module)
    return f"{module}.{attr}"


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
    for key in (CONFIG_KEY, RUN_KEY):
        where = not_plain(checkpoint.get(key), key)
        if where is not None:
            raise CheckpointError(
                f"ckpt_path={path}: {where} is not plain data (expected strings, numbers, "
                "lists and mappings with string keys)"
            )
    problem = state_dict_problem(checkpoint["state_dict"])
    if problem is not None:
        raise CheckpointError(f"ckpt_path={path}: {problem}")
    return checkpoint


def state_dict_problem(state: Any, where: str = "state_dict") -> str | None:
    """What makes ``state`` no state dict (a mapping of parameter names to tensors), in words
    naming the entry, or None when it is one."""
    expected = "expected a mapping of parameter names to tensors"
    if not isinstance(state, dict):
        return f"its {where} holds a {type(state).__name__}; {expected}"
    for key, value in state.items():
        if not isinstance(key, str):
            return f"its {where} has the key {key!r}; {expected}"
        if not isinstance(value, torch.Tensor):
            return f"its {where}[{key!r}] holds a {type(value).__name__}; {expected}"
    return None


def not_plain(data: Any, where: str) -> str | None:
    """The key path of the first value in ``data`` that is not plain data, or None."""
    if isinstance(data, dict):
        for key, value in data.items():
            if not isinstance(key, str):
                return f"{where}[{key!r}]"
            found = not_plain(value, f"{where}.{key}")
            if found is not None:
                return found
        return None
    if isinstance(data, list | tuple):
        for i, value in enumerate(data):
            found = not_plain(value, f"{where}[{i}]")
            if found is not None:
                return found
        return None
    return None if isinstance(data, _PLAIN_TYPES) else f"{where} ({type(data).__name__})"
