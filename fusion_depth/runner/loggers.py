"""Experiment-logger factories that need more than a plain ``_target_``."""

from __future__ import annotations

import csv
import netrc
import os
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from lightning.pytorch.loggers import CSVLogger, WandbLogger

from fusion_depth.runner.redaction import redact_overrides, redact_secrets


def wandb_logged_in() -> bool:
    """True when W&B credentials exist (WANDB_API_KEY or a ``wandb login`` netrc entry)."""
    if os.environ.get("WANDB_API_KEY"):
        return True
    try:
        path = os.environ.get("NETRC") or str(Path.home() / ".netrc")
        hosts = netrc.netrc(path).hosts
    except (FileNotFoundError, netrc.NetrcParseError, OSError):
        return False
    return any("wandb" in host for host in hosts)


@contextmanager
def _argv_redacted() -> Iterator[None]:
    """``sys.argv`` without secrets for the duration: W&B records the command line in its run
    (``+hydra.job.env_set.WANDB_API_KEY=...`` is a legitimate override)."""
    argv = sys.argv
    sys.argv = redact_overrides(argv)
    try:
        yield
    finally:
        sys.argv = argv


class RedactingWandbLogger(WandbLogger):
    """A WandbLogger whose run records the command line with secrets redacted."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # Lightning passes anonymous=None to wandb.init, which then warns on every run that the
        # setting "has no effect and will be removed": a warning no user can act on.
        if self._wandb_init.get("anonymous") is None:
            self._wandb_init.pop("anonymous", None)

    @property
    def experiment(self) -> Any:
        with _argv_redacted():
            return super().experiment


def wandb_mode_offline() -> bool:
    """True when the environment asks W&B to stay on the machine (WANDB_MODE=offline or
    dryrun): then no run goes online, even with credentials present."""
    return os.environ.get("WANDB_MODE", "").strip().lower() in ("offline", "dryrun")


def _hydra_run_identity() -> tuple[str | None, str | None]:
    """(run name from the overrides, sweep group) of the current Hydra job, if any; a secret
    in an override (``x.api_key=...``) is redacted."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
    except (ImportError, ValueError):
        return None, None
    name = hc.job.override_dirname or None
    group = None
    if hc.mode == RunMode.MULTIRUN:
        group = "_".join(Path(hc.sweep.dir).parts[-2:])
    return redact_secrets(name), redact_secrets(group)


def wandb_logger(
    project: str = "fusion-depth",
    save_dir: str = ".",
    offline: bool | None = None,
    name: str | None = None,
    group: str | None = None,
    tags: Sequence[str] = (),
    id: str | None = None,  # noqa: A002 - W&B's name for it
) -> WandbLogger:
    """A WandbLogger that is offline unless the user is logged in (and WANDB_MODE is not
    offline) or asks otherwise.

    Runs are named after their overrides and grouped per sweep, so the W&B UI compares the
    jobs of one grid side by side. ``id``: the W&B run to create or continue (train passes
    the interrupted run's when it resumes).
    """
    if offline is None:
        offline = wandb_mode_offline() or not wandb_logged_in()
    auto_name, auto_group = _hydra_run_identity()
    Path(save_dir).mkdir(parents=True, exist_ok=True)
    return RedactingWandbLogger(
        project=project,
        save_dir=save_dir,
        offline=offline,
        name=name or auto_name,
        group=group or auto_group,
        tags=list(tags),
        log_model=False,
        id=id,
        resume="allow" if id else None,
    )


class ResumableCSVLogger(CSVLogger):
    """Lightning's CSVLogger (which Lightning saves after every logged row, so a kill loses
    none), whose ``metrics.csv`` continues the interrupted run's when a run resumes at
    optimizer step ``resume_step``.

    The rows of work done before that step are kept (their ``step`` column, Lightning's count of
    optimizer steps taken before the row was logged, is below ``resume_step``); later rows
    belong to work the resumed run redoes, and are dropped so they are not written twice.
    ``resume_row``, the row Lightning logs right after the checkpoint was written (see
    :func:`fusion_depth.runner.callbacks.pending_log_row`), is added when a kill came before it.
    Lightning's own CSVLogger deletes the file when it starts.
    """

    def __init__(
        self,
        *args: Any,
        resume_step: int | None = None,
        resume_row: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self._resume_step = resume_step
        self._resume_row = resume_row

    @property
    def experiment(self) -> Any:
        if self._experiment is not None:
            return self._experiment
        path = Path(self.log_dir) / "metrics.csv"
        kept = _rows_before(path, self._resume_step) if self._resume_step else None
        writer = super().experiment  # deletes an existing metrics.csv
        header, rows = kept or ([], [])
        if self._resume_row and not any(_same_row(r, self._resume_row) for r in rows):
            rows.append({k: str(v) for k, v in self._resume_row.items()})
            header = sorted(set(header) | set(self._resume_row))
        if rows:
            writer.metrics_keys = header
            writer.metrics = rows
            writer.save()
        return writer


def _rows_before(path: Path, step: int) -> tuple[list[str], list[dict]] | None:
    """(header, rows) of a Lightning ``metrics.csv`` whose ``step`` is below ``step``; a last
    line cut short by a kill is left out."""
    try:
        text = path.read_text()
    except OSError:
        return None
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines = lines[:-1]
    reader = csv.DictReader(lines)
    header = list(reader.fieldnames or [])
    rows = []
    for row in reader:
        try:
            if None not in row and int(row["step"]) < step:
                rows.append(row)
        except (KeyError, TypeError, ValueError):
            continue
    return (header, rows) if header and "step" in header else None


def _same_row(row: dict[str, str], logged: dict[str, Any]) -> bool:
    """Whether a CSV row (strings) holds the values of ``logged``."""
    try:
        return all(float(row.get(k) or "nan") == float(v) for k, v in logged.items())
    except (TypeError, ValueError):
        return False


def csv_logger(
    save_dir: str,
    name: str = "csv",
    version: str | int = "",
    resume_step: int | None = None,
    resume_row: dict[str, Any] | None = None,
) -> ResumableCSVLogger:
    """A :class:`ResumableCSVLogger` writing ``<save_dir>/<name>/<version>/metrics.csv``
    (``resume_step``, ``resume_row``: train passes where it resumes)."""
    return ResumableCSVLogger(
        save_dir, name=name, version=version, resume_step=resume_step, resume_row=resume_row
    )


@contextmanager
def closing(logger: Any) -> Iterator[Any]:
    """Finish the logger's W&B run on leaving, also on error.

    Lightning's WandbLogger leaves the run open, and the next WandbLogger in the same process
    (the next job of a Hydra multirun) would then log into it; finishing each job's run keeps
    the jobs of a sweep apart.
    """
    failed = True
    try:
        yield logger
        failed = False
    finally:
        if isinstance(logger, WandbLogger) and logger._experiment is not None:
            import wandb

            if wandb.run is not None:
                wandb.finish(exit_code=1 if failed else 0)
