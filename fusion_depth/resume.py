"""Where a run starts: not at all (it finished before), from its own last checkpoint, or afresh.

Run directories are named after the run's overrides (``conf/hydra/default.yaml``), so the same
command finds the same directory again: after a kill, a pre-emption or a failed sweep job it
continues from ``checkpoints/last.ckpt`` (``resume=auto``), and a finished run is not trained
again (``sweep.skip_done=true``).
"""

from __future__ import annotations

import json
import logging
import uuid
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fusion_depth.checkpoint import RUN_KEY, CheckpointError, load_weights_only
from fusion_depth.runs import FAILURE_FILE, METRICS_FILE, PER_IMAGE_FILE, TRACEBACK_FILE

log = logging.getLogger(__name__)

RESUME_MODES = ("auto", "never")
LAST_CHECKPOINT = "last.ckpt"


@dataclass
class RunStart:
    """What :func:`plan_start` decided."""

    finished: dict | None = None  # the finished run's metrics.json: nothing to train
    checkpoint: Path | None = None  # resume from this checkpoint
    wandb_id: str = ""  # the W&B run to log into (the interrupted run's, when resuming)


def override_key(override: str) -> str:
    """``a.b`` of an override ``+a.b=1`` / ``~a.b`` / ``a.b=1``."""
    return override.split("=", 1)[0].lstrip("+~")


def identity_overrides(overrides: Sequence[str], excluded: Collection[str]) -> list[str]:
    """The overrides that make a run what it is: without ``excluded`` keys (``resume``, the
    logger, loader workers: ``hydra.job.config.override_dirname.exclude_keys``), sorted."""
    return sorted(o for o in overrides if override_key(o) not in set(excluded))


def finished_results(output_dir: Path) -> dict | None:
    """The run's ``metrics.json`` if it holds a finished run's results, else None."""
    path = output_dir / METRICS_FILE
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if isinstance(data, dict) and data.get("status") == "ok" and isinstance(data.get("test"), dict):
        return data
    return None


def _check_same_run(
    where: Path, stored: Any, overrides: list[str], excluded: Collection[str]
) -> None:
    stored = identity_overrides(stored or [], excluded) if isinstance(stored, list) else None
    if stored is not None and stored != overrides:
        raise ValueError(
            f"{where} belongs to another run (overrides {' '.join(stored) or '(none)'}), not to "
            f"this one ({' '.join(overrides) or '(none)'}): give this run its own "
            "hydra.run.dir, or resume=never to replace that run"
        )


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
) -> RunStart:
    """Decide how the run in ``output_dir`` starts.

    - ``skip_done`` and a finished ``metrics.json`` there: nothing to do (its results).
    - ``resume=auto`` and ``checkpoint_dir/last.ckpt``: continue from it, in its W&B run.
    - otherwise from scratch; ``resume=never`` first removes a previous run's results and
      checkpoints, so nothing stale is mistaken for this run's.

    ``overrides`` (already filtered by :func:`identity_overrides`) must match those recorded in
    the results or checkpoint found, so a shared ``hydra.run.dir`` never resumes another
    configuration. A failure record from an earlier attempt is removed either way.
    """
    if resume not in RESUME_MODES:
        raise ValueError(f"resume={resume!r}: expected one of {list(RESUME_MODES)}")
    fresh = RunStart(wandb_id=uuid.uuid4().hex[:8])
    if skip_done and (finished := finished_results(output_dir)) is not None:
        where = output_dir / METRICS_FILE
        _check_same_run(where, finished.get("run", {}).get("overrides"), overrides, excluded)
        return RunStart(finished=finished)
    for name in (FAILURE_FILE, TRACEBACK_FILE):
        (output_dir / name).unlink(missing_ok=True)
    if checkpoint_dir is None:
        return fresh
    if resume == "never":
        _clear_previous(output_dir, checkpoint_dir)
        return fresh
    last = checkpoint_dir / LAST_CHECKPOINT
    if not last.is_file():
        return fresh
    try:
        identity = load_weights_only(last, mmap=True).get(RUN_KEY) or {}
    except CheckpointError as err:
        raise CheckpointError(f"{err}; resume=never starts this run over") from err
    _check_same_run(last, identity.get("overrides"), overrides, excluded)
    return RunStart(checkpoint=last, wandb_id=identity.get("wandb_id") or fresh.wandb_id)
