"""Loading a trained model back from a checkpoint, without executing code from the file.

Checkpoints are read with ``torch.load(weights_only=True)``, which only rebuilds tensors and
plain containers. Training stores its run config in every checkpoint (``fusion_depth_config``)
as plain data, without Hydra's instantiation keys (:func:`plain_config`). A checkpoint that has
one anywhere (``_target_``, ``_partial_``, ...) is refused before anything else is done with it.
The network is rebuilt from the known ``model.net`` keys, and the dataset from its name in the
package's own table (:data:`fusion_depth.data.READERS`), with the stored reader arguments
checked against that reader's constructor.
"""

from __future__ import annotations

import _compat_pickle  # pickle's own Python 2 → 3 name table
import functools
import inspect
import os
import pickle
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from hydra.errors import CompactHydraException
from hydra.utils import instantiate
from lightning.pytorch.plugins.io import TorchCheckpointIO

from fusion_depth.data import READERS, cache_dir, reader_class
from fusion_depth.models import DEFAULT_MODEL, DepthModel, create_model, model_arguments
from fusion_depth.runs import write_atomic

CONFIG_KEY = "fusion_depth_config"
RUN_KEY = "fusion_depth_run"
# Hydra's instantiation keys: a config holding one names code to import and call.
INSTANTIATION_KEYS = ("_target_", "_partial_", "_args_", "_recursive_", "_convert_")
# What records a model's dataset, by the option that names the file (LoadedModel.key).
_RECORD = {"ckpt_path": "run config", "model_file": "sidecar"}
_PLAIN_TYPES = (str, int, float, bool, type(None))
# Network arguments a checkpoint never sets: its own weights replace ImageNet's.
_NOT_FROM_CHECKPOINT = ("pretrained", "weights", "association_weights")  # files read at build time


class CheckpointError(ValueError, CompactHydraException):
    """A checkpoint that cannot be used as asked; the message names the file and the problem
    (Hydra prints it alone, without a traceback)."""


class CheckpointWriteError(OSError, CompactHydraException):
    """A checkpoint could not be written (e.g. a full disk); the previous one is intact."""


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


@dataclass
class LoadedModel:
    """A network rebuilt from a checkpoint, with the run config it was trained with (or an
    exported model file run by an engine, :func:`fusion_depth.exporting.runtime.load_exported`:
    then ``key`` is ``model_file`` and ``config`` holds what its sidecar records)."""

    net: DepthModel
    config: dict[str, Any]
    path: Path
    run: dict[str, Any] | None = None  # the training run's identity, when train recorded it
    key: str = "ckpt_path"  # the option that named ``path``, for messages

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
    except (RuntimeError, EOFError, OSError) as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
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
        where = _not_plain(checkpoint.get(key), key)
        if where is not None:
            raise CheckpointError(
                f"ckpt_path={path}: {where} is not plain data (expected strings, numbers, "
                "lists and mappings with string keys)"
            )
    return checkpoint


def _not_plain(data: Any, where: str) -> str | None:
    """The key path of the first value in ``data`` that is not plain data, or None."""
    if isinstance(data, dict):
        for key, value in data.items():
            if not isinstance(key, str):
                return f"{where}[{key!r}]"
            found = _not_plain(value, f"{where}.{key}")
            if found is not None:
                return found
        return None
    if isinstance(data, list | tuple):
        for i, value in enumerate(data):
            found = _not_plain(value, f"{where}[{i}]")
            if found is not None:
                return found
        return None
    return None if isinstance(data, _PLAIN_TYPES) else f"{where} ({type(data).__name__})"


def check_expected(
    config: dict[str, Any],
    path: Path,
    fusion: str | None = None,
    backbone: str | None = None,
    option: str = "ckpt_path",
) -> None:
    """Fail when the caller asked for another fusion mode or backbone than the checkpoint
    (``option``: the key that named ``path``) has."""
    trained = {"fusion": config["fusion"]["mode"], "backbone": config["backbone"]["name"]}
    for key, wanted in (("fusion", fusion), ("backbone", backbone)):
        if wanted is not None and wanted != trained[key]:
            raise CheckpointError(
                f"{option}={path} was trained with {key}={trained[key]}, but {key}={wanted} "
                f"was asked for: drop the {key}= override or pick a {key}={wanted} checkpoint"
            )


def load_model(
    path: str | os.PathLike, fusion: str | None = None, backbone: str | None = None
) -> LoadedModel:
    """Rebuild the network of a training checkpoint and load its weights (eval mode, CPU).

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
    # The network by its name in the package's table (checkpoints from before models had names
    # hold the paper's), with the stored arguments its constructor takes; pretrained=False: the
    # checkpoint's weights replace ImageNet's, which need not be on disk.
    try:
        name = net_config.get("name", DEFAULT_MODEL)
        arguments = set(model_arguments(name)) - set(_NOT_FROM_CHECKPOINT)
        kwargs = {k: net_config[k] for k in arguments if k in net_config}
        net = create_model(name, **kwargs, pretrained=False)
    except (ValueError, TypeError, KeyError, AttributeError) as err:
        raise CheckpointError(
            f"ckpt_path={path}: its model.net config cannot be built ({err})"
        ) from err
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
    ``conf/``) when given, else the one the checkpoint was trained on (see :func:`make_reader`).
    """
    if chosen is not None:
        if "reader" not in chosen:  # e.g. experiment=smoke sets dataset sizes without a dataset=
            raise ValueError(
                f"dataset settings {sorted(chosen)} were given but no dataset was chosen: add "
                "dataset=<name> (e.g. dataset=procedural) to use them, or leave them out to use "
                f"the dataset {loaded.key}={loaded.path} was trained on"
            )
        return chosen
    block = loaded.config.get("dataset")
    if not isinstance(block, dict) or not isinstance(block.get("reader"), dict):
        record = _RECORD.get(loaded.key, "record")
        raise CheckpointError(
            f"{loaded.key}={loaded.path}: its {record} records no dataset reader; pass "
            "dataset=<name> to choose the dataset"
        )
    name = block.get("name")
    if not isinstance(name, str) or name not in READERS:
        raise CheckpointError(
            f"{loaded.key}={loaded.path}: dataset.name={name!r} is not one of "
            f"{sorted(READERS)}; pass dataset=<name> to choose the dataset"
        )
    # What the reader needs installed is checked by importing it from the table (make_reader),
    # never by a module name the file gives.
    return {k: v for k, v in block.items() if k != "requires"}


def make_reader(
    block: dict[str, Any], path: Path | None = None, key: str = "ckpt_path"
) -> Callable[..., Any]:
    """The reader of a dataset block, as a callable taking ``split=``.

    With ``path`` (the block came from that checkpoint, or the model file of ``key=model_file``
    whose sidecar recorded it), the reader class is looked up by
    ``dataset.name`` in :data:`fusion_depth.data.READERS` and the stored ``dataset.reader``
    arguments must be plain data naming that constructor's parameters. Where the reader writes
    (generated or prepared data, the reader class's ``writes_into``) is this machine's cache
    folder, not the one the file names. Otherwise (a block composed from ``conf/``) Hydra
    instantiates it as configured.

    Raises:
        CheckpointError: an unknown dataset, an argument the reader does not take, or a value
            that is not plain data (naming the key).
    """
    if path is None:
        return instantiate(block["reader"])
    name = block["name"]
    try:
        cls = reader_class(name)
    except ImportError as err:
        raise CheckpointError(
            f"{key}={path}: dataset={name} needs a package that is not installed ({err})"
        ) from err
    params = inspect.signature(cls).parameters
    args = dict(block["reader"])
    for arg, value in args.items():
        if arg not in params or arg == "split":
            raise CheckpointError(
                f"{key}={path}: dataset.reader.{arg} is not an argument of the {name} "
                f"reader; expected some of {sorted(k for k in params if k != 'split')}"
            )
        if _not_plain(value, arg) is not None:
            raise CheckpointError(
                f"{key}={path}: dataset.reader.{arg} holds a {type(value).__name__}; "
                "expected plain data (strings, numbers, lists)"
            )
    arg, folder = cls.writes_into
    if arg in args:
        args[arg] = str(Path(cache_dir()) / folder)
    return functools.partial(cls, **args)


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

        failed: list[OSError] = []  # what the file system said, under torch's own error

        def write(tmp: Path) -> None:
            with tmp.open("wb") as f:
                torch.save(checkpoint, _ReportingFile(f, failed))
                f.flush()
                os.fsync(f.fileno())

        try:
            write_atomic(path, write, suffix=".ckpt.tmp")
        except (OSError, RuntimeError) as err:
            cause = failed[0] if failed else err
            reason = cause.strerror if isinstance(cause, OSError) and cause.strerror else cause
            failure = CheckpointWriteError(
                f"could not write the checkpoint {path} ({reason}; "
                f"{_free_space(Path(path).parent)} free there); the previous checkpoint there, "
                "if any, is intact"
            )
            failure.errno = getattr(cause, "errno", None)
            raise failure from err

    def load_checkpoint(
        self, path: Any, map_location: Any | None = None, weights_only: bool | None = None
    ) -> dict[str, Any]:
        return load_weights_only(path, map_location=map_location)


class _ReportingFile:
    """A binary file for ``torch.save`` that keeps the OSError of a failed write: torch turns
    it into its own ``RuntimeError`` (inline_container), which no longer says why."""

    def __init__(self, file: Any, failed: list[OSError]) -> None:
        self._file = file
        self._failed = failed

    def write(self, data: Any) -> int:
        try:
            return self._file.write(data)
        except OSError as err:
            self._failed.append(err)
            raise

    def __getattr__(self, name: str) -> Any:
        return getattr(self._file, name)


def _free_space(folder: Path) -> str:
    """Free space on ``folder``'s file system, e.g. ``'12.3 MB'`` (``'unknown'`` if unreadable)."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return "unknown space"
    return f"{free / 1e6:.1f} MB"
