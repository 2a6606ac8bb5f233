"""Where a run starts: not at all (it finished before), from its own last checkpoint, or afresh.

Run directories are named after the run's overrides (``conf/hydra/default.yaml``), so the same
command finds the same directory again: after a kill, a pre-emption or a failed sweep job it
continues from ``checkpoints/last.ckpt`` (``resume=auto``), and a finished run is not trained
again (``sweep.skip_done=true``). The folder must hold the same run: the same overrides, and the
same resolved config, so a default or config file changed since (a new package version, an edited
``conf/``) never continues, or passes off as finished, a run of the old configuration.
"""

from __future__ import annotations

import fcntl
import logging
import os
import socket
import time
import uuid
from collections.abc import Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from fusion_depth.errors import UserError
from fusion_depth.runner.protocol import BEFORE_PRESETS
from fusion_depth.runner.record import METRICS_FILE, RunIdentity, read_finished
from fusion_depth.runner.run_folder import (
    FAILURE_FILE,
    PER_IMAGE_FILE,
    RESOLVED_CONFIG_FILE,
    TRACEBACK_FILE,
)
from fusion_depth.utils.atomic import remove_orphaned_temporaries
from fusion_depth.utils.checkpoint_file import (
    CONFIG_KEY,
    RUN_KEY,
    CheckpointError,
    load_weights_only,
    plain_config,
)
from fusion_depth.utils.schema import BOOLEAN, Schema, one_of

log = logging.getLogger(__name__)

RESUME_MODES = ("auto", "never")
LAST_CHECKPOINT = "last.ckpt"
LAST_CHECKPOINT_STATE = "LastCheckpoint"  # its callback state's key in a checkpoint
LOCK_FILE = ".run.lock"


@dataclass
class RunStart:
    """What :func:`plan_start` decided."""

    finished: dict | None = None  # the finished run's metrics.json (contents): nothing to train
    checkpoint: Path | None = None  # resume from this checkpoint
    wandb_id: str = ""  # the W&B run to log into (the interrupted run's, when resuming)
    global_step: int = 0  # the checkpoint's optimizer steps (0 when starting afresh)
    pending_log_row: dict | None = None  # the log row written right after that checkpoint


class OtherRunError(ValueError, UserError):
    """The run folder holds another configuration's run."""


class RunLockedError(RuntimeError, UserError):
    """Another live process is using the run folder."""


class RunLock:
    """One run folder, one process: an exclusive ``flock`` on ``<run dir>/.run.lock``, which
    records the holder's PID and host for the message a second process gets.

    The kernel drops the lock when its process dies, however it dies, so a lock left by a killed
    run is simply taken over by the next command. Use as a context manager.

    Raises:
        RunLockedError: a live process holds the lock (named by PID and host).
    """

    def __init__(self, run_dir: str | os.PathLike) -> None:
        self.path = Path(run_dir) / LOCK_FILE
        self._fd: int | None = None

    def __enter__(self) -> RunLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:  # never through a symbolic link: the lock file is written to
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as err:
            raise RunLockedError(
                f"{self.path}: cannot be used as the run's lock file ({err.strerror}); expected "
                "a regular file or none: remove it"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _lock_holder(fd)
            os.close(fd)
            raise RunLockedError(
                f"{self.path.parent} is in use by {holder}: wait for it to finish (or stop it); "
                "two processes in one run folder would train over each other"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on host {socket.gethostname()}\n".encode())
        self._fd = fd
        return self

    def __exit__(self, *exc: object) -> None:
        if self._fd is not None:
            os.close(self._fd)  # releases the flock; the file stays (removing it would race)
            self._fd = None


def _lock_holder(fd: int) -> str:
    """What the holder wrote into the lock file (it writes right after locking: wait briefly)."""
    for _ in range(20):
        text = os.pread(fd, 200, 0).decode(errors="replace").strip()
        if text:
            return f"process {text.removeprefix('pid ')}"
        time.sleep(0.05)
    return "another process"


def is_lead_process() -> bool:
    """False in the ranks > 0 that a cluster launcher (SLURM, torchrun) starts for one run:
    they share the lead process's run folder and lock."""
    for variable in ("RANK", "SLURM_PROCID"):
        value = os.environ.get(variable)
        if value is not None and value.strip().isdigit():
            return int(value) == 0
    return True


def _run_folders(output_dir: Path, checkpoint_dir: Path | None) -> list[Path]:
    """Where a run writes: its folder, the folders right inside it (checkpoints, val_panels)
    and ``checkpoint_dir``; not deeper (a run folder may be a user's folder, with trees of
    their own below it, such as W&B's)."""
    inside = []
    if output_dir.is_dir():
        inside = sorted(p for p in output_dir.iterdir() if p.is_dir() and not p.is_symlink())
    folders = [output_dir, *inside, *([checkpoint_dir] if checkpoint_dir else [])]
    return list(dict.fromkeys(folders))


def remove_leftovers(output_dir: Path, checkpoint_dir: Path | None, keep: Collection[Path]) -> None:
    """Remove what an interrupted attempt left (the caller holds the run lock): temporary files
    of writes it never finished, and checkpoints its resumed state does not know (``keep``:
    ``last.ckpt`` and the best checkpoints it records). Such a checkpoint was written after
    ``last.ckpt``, by work that is about to be redone."""
    if not is_lead_process():  # the lead process holds the lock and cleans up
        return
    for folder in _run_folders(output_dir, checkpoint_dir):
        # Every temporary the run writes (test_panels.npz's, a checkpoint's, a panel's), by
        # the one rule of fusion_depth.utils.atomic.is_temporary.
        for path in remove_orphaned_temporaries(folder, folder_locked=True):
            log.info("removed %s, left by an interrupted attempt", path)
    if checkpoint_dir is not None and checkpoint_dir.is_dir():
        # By name: a recorded path may be relative to another working directory.
        known = {Path(p).name for p in keep}
        for path in sorted(p for p in checkpoint_dir.glob("*.ckpt") if p.name not in known):
            log.info("removing %s, left by an interrupted attempt", path)
            path.unlink(missing_ok=True)


def override_key(override: str) -> str:
    """``a.b`` of an override ``+a.b=1`` / ``~a.b`` / ``a.b=1``."""
    return override.split("=", 1)[0].lstrip("+~")


def identity_overrides(overrides: Sequence[str], excluded: Collection[str]) -> list[str]:
    """The overrides that make a run what it is: without ``excluded`` keys (``resume``, the
    logger, loader workers: ``hydra.job.config.override_dirname.exclude_keys``), sorted."""
    return sorted(o for o in overrides if override_key(o) not in set(excluded))


def finished_results(output_dir: Path) -> dict | None:
    """The contents of the run's ``metrics.json`` if it holds a finished run's results
    (:func:`fusion_depth.runner.record.read_finished`: status ok, test metrics, at least one
    optimizer step trained), else None."""
    record = read_finished(output_dir)
    return record.to_json() if record is not None else None


# Config keys added since a run folder may have been written, with the value that computes as
# the run did without them: a stored config that lacks one of these is the same run.
# The prior group (0.3.0) at prior=none, which computes as a run without it did.
_NO_PRIOR = {
    "name": "none",
    "weights": None,
    "input_size": None,
    "kind": None,
    "max_depth": None,
    "dropout": 0.0,
    "cache": False,
}
_NO_GEOMETRY = {
    "saturation": None,
    "color_each": False,
    "crop": None,
    "crop_center": None,
    "crop_placement": "uniform",
    "scale": None,
    "rotation": 0.0,
    "resample": "bilinear",
    "outlier_filter": None,
}
_ADDED_KEYS: dict[str, Any] = {
    **{
        f"{block}.{key}": value
        for block in ("eval", "model.evaluation")
        for key, value in BEFORE_PRESETS.items()
    },
    **{
        f"{block}.{key}": value
        for block in ("prior", "model.net.prior")
        for key, value in _NO_PRIOR.items()
    },
    "model.net.fake_point_probability": 0.0,  # RadarNet's fake points in its association stage
    "model.net.lidar_loss_weight": 0.0,
    "model.net.fake_column_noise": None,  # RadarNet's fusion loss on the measured pixels
    "dataset.reader.lidar_keyframes": 0,  # nuScenes: RadarNet's merged target, not asked for
    "dataset.reader.lidar_removed": ["vehicle", "human"],
    # the built-in dataset's camera (a source pool's other cameras): the car's
    "dataset.reader.camera_height": [1.4, 1.7],
    "dataset.reader.fov_range": None,
    # the augmentation's saturation and geometry (each model's own augmentation), all off
    **{
        f"{block}.{key}": value
        for block in ("augment", "model.augmentation")
        for key, value in _NO_GEOMETRY.items()
    },
}
# Nodes a later version no longer writes, that computed nothing themselves: 0.2.0's `recipe:` (a
# dataset recipe's encoder and loss weights, which reached the run only through the backbone,
# loss and scheduler values, compared as they are).
_REMOVED_NODES = ("recipe",)

# Where a run's folder and the dataset cache are: not part of what it computes, so a run folder
# that was moved, or a cache that moved, still resumes.
_PLACES = {"output_dir": "<run folder>", "cache_dir": "<cache>"}
_MAX_CHANGES_SHOWN = 4


def _leaves(tree: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    for key, value in tree.items():
        if isinstance(value, Mapping):
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def _comparable(config: Mapping[str, Any], excluded: Collection[str]) -> dict[str, Any]:
    paths = config.get("paths") if isinstance(config.get("paths"), Mapping) else {}
    places = [(str(paths[k]), v) for k, v in _PLACES.items() if isinstance(paths.get(k), str)]
    places.sort(key=lambda place: -len(place[0]))  # the run folder may lie inside the cache
    skipped = (*excluded, "paths")
    out = {}
    for key, value in _leaves(config):
        if any(key == e or key.startswith(f"{e}.") for e in skipped):
            continue
        for where, placeholder in places:
            if isinstance(value, str) and where and where in value:
                value = value.replace(where, placeholder)
        out[key] = value
    return out


def config_changes(
    stored: Mapping[str, Any], current: Mapping[str, Any], excluded: Collection[str] = ()
) -> list[str]:
    """What differs between a run config a run folder recorded and this run's, as
    ``key: stored → current`` (``absent`` for a missing key), sorted by key.

    Keys that do not change what a run computes are left out: a key added since, that the
    stored config lacks, at the value that computes as before (:data:`_ADDED_KEYS`: the
    evaluation presets' keys at ``eval=paper``'s values, the prior's at ``prior=none``); a node
    no longer written (:data:`_REMOVED_NODES`); ``excluded`` ones (the override keys of
    ``hydra.job.config.override_dirname.exclude_keys``, with everything below them) and
    ``paths``; the run folder and the dataset cache, wherever a value names them, count as the
    same place (each config's own ``paths.output_dir`` and ``paths.cache_dir``). Both are
    compared as checkpoints store them
    (:func:`~fusion_depth.utils.checkpoint_file.plain_config`)."""
    old = _comparable(plain_config(dict(stored)), excluded)
    new = _comparable(plain_config(dict(current)), excluded)
    absent = object()
    changes = []
    for key in sorted(old.keys() | new.keys()):
        before, after = old.get(key, absent), new.get(key, absent)
        if before is absent and key in _ADDED_KEYS and after == _ADDED_KEYS[key]:
            continue  # a key added later, at the value that computes as before
        if after is absent and key.split(".")[0] in _REMOVED_NODES:
            continue
        if before != after:
            shown = ["absent" if v is absent else repr(v) for v in (before, after)]
            changes.append(f"{key}: {shown[0]} → {shown[1]}")
    return changes


def _check_same_run(
    where: Path,
    stored: Any,
    overrides: list[str],
    excluded: Collection[str],
    stored_config: Any = None,
    config: Mapping[str, Any] | None = None,
) -> None:
    stored = identity_overrides(stored or [], excluded) if isinstance(stored, list) else None
    if stored is not None and stored != overrides:
        raise OtherRunError(
            f"{where} belongs to another run (overrides {' '.join(stored) or '(none)'}), not to "
            f"this one ({' '.join(overrides) or '(none)'}): give this run its own "
            "hydra.run.dir, or resume=never to replace that run"
        )
    if config is None or not isinstance(stored_config, Mapping):
        return  # a folder from before run configs were recorded: the overrides decide
    changes = config_changes(stored_config, config, excluded)
    if changes:
        more = len(changes) - _MAX_CHANGES_SHOWN
        shown = "; ".join(changes[:_MAX_CHANGES_SHOWN]) + (f"; and {more} more" if more > 0 else "")
        raise OtherRunError(
            f"{where} holds a run of the same command with another configuration ({shown}): "
            "the defaults or config files changed since it ran. resume=never replaces it; "
            "another hydra.run.dir keeps it"
        )


def _recorded_config(output_dir: Path) -> Any:
    """The run config a finished run wrote (``config_resolved.yaml``, read as plain data), or
    None when there is none or it cannot be read (then its overrides alone decide)."""
    path = output_dir / RESOLVED_CONFIG_FILE
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, RecursionError, yaml.YAMLError) as err:
        log.warning("%s: not readable (%s); comparing the run's overrides only", path, err)
        return None


def recorded_precision(output_dir: Path, checkpoint_dir: Path | None) -> str | None:
    """The ``trainer.precision`` the run in ``output_dir`` ran in, as recorded
    (``config_resolved.yaml``, else its ``last.ckpt``'s run config), or None where there is
    nothing to resume or skip (no ``last.ckpt``, no ``metrics.json``) or no readable record (a
    damaged file is named later, by :func:`plan_start`)."""
    last = None if checkpoint_dir is None else checkpoint_dir / LAST_CHECKPOINT
    resumable = last is not None and last.is_file()
    if not resumable and not (output_dir / METRICS_FILE).is_file():
        return None  # nothing to go on from: a new run, whatever an earlier attempt recorded
    config = _recorded_config(output_dir)
    if not isinstance(config, Mapping) and resumable:
        try:
            config = load_weights_only(last, mmap=True).get(CONFIG_KEY)
        except (CheckpointError, OSError, AttributeError):
            return None
    trainer = config.get("trainer") if isinstance(config, Mapping) else None
    precision = trainer.get("precision") if isinstance(trainer, Mapping) else None
    return precision if isinstance(precision, str) else None


def _clear_previous(output_dir: Path, checkpoint_dir: Path) -> None:
    """Remove a previous run's results and checkpoints (``resume=never``), naming them."""
    stale = [output_dir / name for name in (METRICS_FILE, PER_IMAGE_FILE)]
    stale += sorted(checkpoint_dir.glob("*.ckpt")) if checkpoint_dir.is_dir() else []
    stale = [p for p in stale if p.exists()]
    if stale:
        log.warning(
            "resume=never: starting over in %s; removing the previous run's %s",
            output_dir,
            ", ".join(str(p.relative_to(output_dir)) for p in stale),
        )
    for path in stale:
        path.unlink(missing_ok=True)  # the other ranks of a SLURM job clear the same files


def plan_start(
    output_dir: Path,
    checkpoint_dir: Path | None,
    resume: str,
    skip_done: bool,
    overrides: list[str],
    excluded: Collection[str] = (),
    config: Mapping[str, Any] | None = None,
) -> RunStart:
    """Decide how the run in ``output_dir`` starts.

    - ``skip_done`` and a finished ``metrics.json`` there (unless ``resume=never``): nothing to
      do (its results).
    - ``resume=auto`` and ``checkpoint_dir/last.ckpt``: continue from it, in its W&B run.
    - otherwise from scratch; ``resume=never`` first removes a previous run's results and
      checkpoints, so nothing stale is mistaken for this run's.

    ``overrides`` (already filtered by :func:`identity_overrides`) must match those recorded in
    the results or checkpoint found, so a shared ``hydra.run.dir`` never resumes another
    configuration; so must ``config`` (this run's resolved config, secrets redacted as it is
    written) match the one recorded there (``config_resolved.yaml`` beside a finished
    ``metrics.json``, the checkpoint's run config), by :func:`config_changes`. A failure record
    from an earlier attempt is removed either way, and so are the leftovers of an interrupted
    attempt (:func:`remove_leftovers`): call it holding the run's :class:`RunLock`.
    """
    if resume not in RESUME_MODES:
        raise ValueError(f"resume={resume!r}: expected one of {list(RESUME_MODES)}")
    fresh = RunStart(wandb_id=uuid.uuid4().hex[:8])
    if skip_done and resume != "never" and (finished := read_finished(output_dir)) is not None:
        where = output_dir / METRICS_FILE
        stored = finished.run.overrides if finished.run is not None else None
        stored_config = _recorded_config(output_dir) if config is not None else None
        _check_same_run(where, stored, overrides, excluded, stored_config, config)
        return RunStart(finished=finished.to_json())
    for name in (FAILURE_FILE, TRACEBACK_FILE):
        (output_dir / name).unlink(missing_ok=True)
    if checkpoint_dir is None:
        remove_leftovers(output_dir, None, keep=())
        return fresh
    if resume == "never":
        _clear_previous(output_dir, checkpoint_dir)
        remove_leftovers(output_dir, checkpoint_dir, keep=())
        return fresh
    last = checkpoint_dir / LAST_CHECKPOINT
    if not last.is_file():
        remove_leftovers(output_dir, checkpoint_dir, keep=())
        return fresh
    try:
        # Also refuses a checkpoint that names code anywhere in it (check_no_code).
        checkpoint = load_weights_only(last, mmap=True)
    except CheckpointError as err:
        raise CheckpointError(f"{err}; resume=never starts this run over") from err
    check_resume_state(checkpoint, last)
    identity = RunIdentity.from_json(checkpoint.get(RUN_KEY) or {})
    _check_same_run(
        last, identity.overrides, overrides, excluded, checkpoint.get(CONFIG_KEY), config
    )
    remove_leftovers(output_dir, checkpoint_dir, keep=[last, *known_checkpoints(checkpoint)])
    state = checkpoint["callbacks"].get(LAST_CHECKPOINT_STATE) or {}
    return RunStart(
        checkpoint=last,
        wandb_id=identity.wandb_id or fresh.wandb_id,
        global_step=int(checkpoint.get("global_step", 0)),
        pending_log_row=state.get("pending_log_row"),
    )


_CHECKPOINT_PATH_KEYS = ("best_model_path", "kth_best_model_path", "last_model_path")


def _refuse(last: Path, what: str) -> CheckpointError:
    return CheckpointError(f"ckpt_path={last}: refused; {what}; resume=never starts this run over")


def check_resume_state(checkpoint: Any, last: Path) -> None:
    """Refuse a ``last.ckpt`` whose training state is not what training writes, before Lightning
    restores it: the run identity and callback states must be mappings, the step an integer,
    the logged row plain numbers, and every checkpoint file a ModelCheckpoint state names must
    lie directly in that state's own folder (Lightning deletes the files it names when better
    ones arrive, and tests the best one).

    Raises:
        CheckpointError: one line naming the key.
    """
    if not isinstance(checkpoint, dict):
        raise _refuse(last, "it is not a mapping")
    if not isinstance(checkpoint.get(RUN_KEY, {}), dict):
        raise _refuse(last, f"{RUN_KEY} is not a mapping")
    step = checkpoint.get("global_step", 0)
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise _refuse(last, f"global_step={step!r} is not a step count")
    callbacks = checkpoint.setdefault("callbacks", {})
    if not isinstance(callbacks, dict) or not all(isinstance(v, dict) for v in callbacks.values()):
        raise _refuse(last, "callbacks is not a mapping of callback states")
    row = (callbacks.get(LAST_CHECKPOINT_STATE) or {}).get("pending_log_row")
    if row is not None and not (
        isinstance(row, dict)
        and all(isinstance(k, str) for k in row)
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in row.values())
    ):
        raise _refuse(last, f"callbacks.{LAST_CHECKPOINT_STATE}.pending_log_row is not a row")
    for name, state in callbacks.items():
        kept = state.get("kept_metrics")  # MajorityCheckpoint's: the kept validation's metrics
        if kept is not None and not (
            isinstance(kept, dict)
            and all(isinstance(k, str) for k in kept)
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in kept.values())
        ):
            raise _refuse(last, f"callbacks[{name!r}].kept_metrics is not metric values")
        folder = state.get("dirpath")
        for path in _named_checkpoints(state):
            inside = (
                isinstance(path, str) and isinstance(folder, str) and ".." not in Path(path).parts
            )
            if not inside or Path(path).parent != Path(folder):
                raise _refuse(last, f"callbacks[{name!r}] names {path!r}, not a file in its folder")


def _named_checkpoints(state: dict) -> list[Any]:
    """The checkpoint files a callback state names (a ModelCheckpoint's best, k-th best, last
    and top-k models; none for other callbacks), as stored: unchecked values."""
    top_k = state.get("best_k_models") or {}
    paths = [state.get(key) for key in _CHECKPOINT_PATH_KEYS]
    paths += list(top_k) if isinstance(top_k, dict) else [top_k]
    return [p for p in paths if p not in (None, "")]


def known_checkpoints(checkpoint: dict) -> list[Path]:
    """The checkpoint files a saved training state refers to (checked by
    :func:`check_resume_state` first): every ModelCheckpoint's best and top-k models."""
    return [
        Path(p) for state in checkpoint["callbacks"].values() for p in _named_checkpoints(state)
    ]


# The values of the keys train reads itself (fusion_depth.utils.schema).
CONFIG_SCHEMA: Schema = {"resume": one_of(*RESUME_MODES), "sweep.skip_done": BOOLEAN}
