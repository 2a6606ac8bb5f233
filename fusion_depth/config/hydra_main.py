"""What every Hydra command line of the package shares (``train``, ``evaluate``, ``predict``,
``export``, ``prepare``; console scripts ``fusion-depth-<command>``):

* **Configs from anywhere.** The configs are read from :data:`~fusion_depth.config.CONF_DIR`
  (``conf/`` of a checkout, or the copy inside an installed package), and the sweep configs of
  ``sweeps/`` are registered by name in Hydra's config store, so ``--config-name
  procedural_weather`` finds them from any working directory (``--config-dir sweeps`` still
  works in a checkout, and picks your own sweep files first).
* **Unknown keys in one line.** ``trainer.max_epoch=3`` gets ``did you mean max_epochs?`` and
  the keys that exist (or, for a key the node's target takes, how to add it with ``+``), read
  from the error Hydra raises when it composes the config, instead of Hydra's struct error.
* **One-line errors.** Errors the package raises about the user's data, config or files (a
  ``ValueError`` or ``OSError`` raised by package code, also from inside a DataLoader worker),
  before the job starts or while it runs, print as one line on stderr, and so do Hydra's own
  errors about the user's files (a run folder it cannot create): Hydra's ``Error executing job
  with overrides`` line and its ``HYDRA_FULL_ERROR`` hint are left out (in a multirun the line
  starts with the failed job's overrides instead). ``HYDRA_FULL_ERROR=1`` shows the full
  traceback, as in Hydra; a bug keeps its traceback and the hint.

The command line goes to Hydra as typed. Run folders are named so that a path a run prints can
be pasted back unquoted (:mod:`fusion_depth.config.run_dirs`); a path of one's own with ``=``,
``,``, spaces or brackets in it is quoted as Hydra's grammar asks (``'ckpt_path="a=b.ckpt"'``),
and the grammar error shows that form. To see Hydra's errors at all, the command sets
``HYDRA_FULL_ERROR=1`` while Hydra runs it (Hydra then raises them rather than printing them
and exiting), and reports them itself, as Hydra would, only shorter.
"""

from __future__ import annotations

import errno
import functools
import os
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.errors import (
    CompactHydraException,
    ConfigCompositionException,
    OverrideParseException,
)
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError

from fusion_depth.config import CONF_DIR, SWEEPS_DIR, target_accepts, unknown_key_error
from fusion_depth.config.arguments import argument_error, config_message
from fusion_depth.errors import CommandError, UserError

# What prints as its message alone: Hydra's compact errors and the package's own.
SHORT_ERRORS = (CompactHydraException, UserError)

_PACKAGE_DIR = Path(__file__).resolve().parents[1]  # fusion_depth/


# --- sweep configs ----------------------------------------------------------------------------


def register_sweeps(config_dir: str | None = None) -> None:
    """Every ``sweeps/<name>.yaml`` as the primary config ``<name>`` in Hydra's config store
    (plain YAML data; idempotent), except names ``config_dir`` (``--config-dir``) has: Hydra
    would merge a file and a stored config of one name as a schema, with a deprecation warning."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for path in sorted(Path(SWEEPS_DIR).glob("*.yaml")):
        if config_dir and (Path(config_dir) / path.name).exists():
            continue
        store.store(name=path.stem, node=OmegaConf.load(path), provider="fusion_depth.sweeps")


# --- unknown keys -----------------------------------------------------------------------------


def unknown_key_message(err: BaseException, overrides: list[str]) -> str | None:
    """The one-line message for Hydra's error about an override that sets a key the config
    lacks (``Could not override 'trainer.max_epoch'``), or None for any other error.

    The key, and the node that lacks it, come from the OmegaConf error Hydra raised it from.
    The message names the first missing part of the override's key and the keys beside it,
    with a suggestion (``trainer.max_epoch: unknown key (did you mean max_epochs?); expected
    one of ...``), or says how to add it with ``+`` when the node's ``_target_`` takes it.

    Args:
        err: the error composing the config raised (Hydra's ``ConfigCompositionException``).
        overrides: the command line's overrides, to find the failing one's value.
    """
    cause = err.__cause__
    if not isinstance(err, ConfigCompositionException) or not isinstance(
        cause, ConfigAttributeError | ConfigKeyError
    ):
        return None
    node, missing = cause.parent_node, cause.full_key
    if not isinstance(node, DictConfig) or not missing:
        return None
    # The override that failed: its key is the missing one, or lies below it (trainr.x=1).
    failing = next(
        (o for o in overrides if f"{o.partition('=')[0]}.".startswith(f"{missing}.")), None
    )
    if failing is None:  # +key or ~key: Hydra's own message says what is wrong
        return None
    key, _, value = failing.partition("=")
    if key == missing and target_accepts(node, str(cause.key)):
        target = node._target_
        return f"{key}: not in this config, but {target} takes it: add it with +{key}={value}"
    allowed = [str(k) for k in node.keys() if not str(k).startswith("_")]
    return str(unknown_key_error(missing, allowed))


# --- short errors -----------------------------------------------------------------------------


def _raised_by_package(err: BaseException) -> bool:
    """Whether the innermost frame of ``err``'s traceback is in this package's code."""
    frames = traceback.extract_tb(err.__traceback__)
    return bool(frames) and Path(frames[-1].filename).resolve().is_relative_to(_PACKAGE_DIR)


def _worker_error(text: str) -> str | None:
    """The original error line of an exception a DataLoader worker re-raised in the main
    process (``Caught X in DataLoader worker process 0. Original Traceback ... X: message``),
    when package code raised it (its frame is among the last lines)."""
    if not text.startswith("Caught ") or "Original Traceback" not in text:
        return None
    lines = [line for line in text.strip().splitlines() if line.strip()]
    last = lines[-1]
    raised_here = any("fusion_depth" in line and "File " in line for line in lines[-4:])
    _, sep, message = last.partition(": ")
    return message if sep and raised_here else None


def _study_without_completed_trial(err: BaseException) -> bool:
    """Whether ``err`` is Optuna's answer to the Optuna sweeper asking, after the last trial, for
    the best one of a study in which every trial failed (a ValueError raised under
    ``Study.best_trial``: "Record does not exist." or "No trials are completed yet.")."""
    frames = traceback.extract_tb(err.__traceback__)
    return isinstance(err, ValueError) and any(
        frame.name == "best_trial" and "optuna" in Path(frame.filename).parts for frame in frames
    )


def _override_message(err: OverrideParseException) -> str:
    """Hydra's grammar error, naming the override, and how to quote a value that has characters
    the grammar reads as syntax (a path of your own with ``=``, ``,`` or spaces in it)."""
    message = f"{err.override}: {str(err).splitlines()[0].strip()}"
    key, sep, value = err.override.partition("=")
    if sep and any(c in value for c in "=, []{}()'\""):
        quote = "'" if '"' not in value else '"'
        inner = '"' if quote == "'" else "'"
        message += f"; quote it: {quote}{key}={inner}{value}{inner}{quote}"
    return message


def _run_folder() -> str | None:
    """The run folder Hydra made for this job, when it has got that far."""
    from hydra.core.hydra_config import HydraConfig

    try:
        return str(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else None
    except Exception:  # noqa: BLE001 - a half-set Hydra config: no folder to name
        return None


def _file_being_written(err: BaseException) -> str | None:
    """The name of a file open for writing in the innermost frames of ``err``'s traceback: what
    a write that failed without naming its file (``f.write`` in Hydra or Lightning) wrote."""
    frames = []
    tb = err.__traceback__
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    for frame in reversed(frames[-3:]):
        for value in frame.f_locals.values():
            name, mode = getattr(value, "name", None), getattr(value, "mode", None)
            if isinstance(name, str) and isinstance(mode, str) and set(mode) & set("wax+"):
                return name
    return None


def _disk_full_message(err: BaseException) -> str | None:
    """One line for a write that failed for want of space, naming where: the file, else (a
    write deep in Hydra or Lightning that did not say) the run folder."""
    if not isinstance(err, OSError) or err.errno not in (errno.ENOSPC, errno.EDQUOT):
        return None
    if err.filename is None and err.strerror and "disk is full" in err.strerror:
        return err.strerror  # the package's own message (a full cache), which names it
    where = err.filename or _file_being_written(err) or _run_folder() or "the output folder"
    return (
        f"{where}: the disk is full ({os.strerror(err.errno)}); free space there or write the "
        "run elsewhere (hydra.run.dir=...), then run the command again"
    )


def user_message(err: BaseException, cfg: DictConfig | None = None) -> str | None:
    """The message to show instead of a traceback for an error about the user's input (data,
    config values, files), or None for anything else (a bug keeps its traceback). An argument of
    the science code is named by its config key, where ``cfg`` (the run's config) sets it."""
    text = str(err).strip()
    argument = argument_error(err)
    if argument is not None:
        return config_message(argument, cfg=cfg)
    full = _disk_full_message(err)
    if full is not None:
        return full
    if _study_without_completed_trial(err):
        return (
            "hparams_search: no trial of the study completed, so it has no best configuration; "
            "each failed trial's error is above and in its run folder's failure.json"
        )
    if isinstance(err, OverrideParseException):
        return _override_message(err)
    if isinstance(err, SHORT_ERRORS):
        return _worker_error(text) or text
    if isinstance(err, OSError | ValueError):
        from_worker = _worker_error(text)
        if from_worker:
            return from_worker
        if isinstance(err, OSError) and err.filename is not None:
            return f"{err.filename}: {err.strerror or type(err).__name__}"
        if _raised_by_package(err) and text:
            return text
    return None


HYDRA_JOB_LINE = "Error executing job with overrides:"


class _WithoutJobLine:
    """``sys.stderr`` while a failed job's error travels up through Hydra: drops the ``Error
    executing job with overrides: [...]`` line Hydra writes before re-raising it (the error
    itself is reported in one line), and passes everything else through."""

    def __init__(self, stream: Any) -> None:
        self.stream = stream

    def write(self, text: str) -> int:
        if text.startswith(HYDRA_JOB_LINE):
            return len(text)
        return self.stream.write(text)

    def __getattr__(self, name: str) -> Any:  # flush, fileno, isatty, encoding, ...
        return getattr(self.stream, name)


# Whether a command of hydra_main reports the job's errors itself (not with HYDRA_FULL_ERROR=1
# set by the user, nor for a config passed in by a caller).
_reporting = False


def _drop_hydra_job_line() -> None:
    """From now until :func:`hydra_main`'s command returns, Hydra's job line is not printed."""
    if _reporting and not isinstance(sys.stderr, _WithoutJobLine):
        sys.stderr = _WithoutJobLine(sys.stderr)


def _in_multirun_job(message: str) -> str:
    """``message``, led by the job's overrides in a multirun (which of its jobs failed)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    try:
        hydra = HydraConfig.get() if HydraConfig.initialized() else None
    except Exception:  # noqa: BLE001 - a half-set Hydra config: no job to name
        hydra = None
    if hydra is None or hydra.mode != RunMode.MULTIRUN:
        return message
    from fusion_depth.runner.redaction import redact_overrides

    overrides = " ".join(redact_overrides(list(hydra.overrides.task))) or "no overrides"
    return f"job {hydra.job.num} ({overrides}): {message}"


def _short_errors(task: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    @functools.wraps(task)  # keeps the module and name Hydra derives the job name from
    def run(cfg: DictConfig) -> Any:
        try:
            return task(cfg)
        except (*SHORT_ERRORS, OSError, ValueError) as err:
            message = user_message(err, cfg)
            if message is None:
                raise
            _drop_hydra_job_line()
            raise CommandError(_in_multirun_job(message)) from err

    return run


def _report(err: Exception) -> None:
    """Print ``err`` as Hydra does without ``HYDRA_FULL_ERROR``, but an error about the user's
    input (:func:`user_message`) as its message alone, in one line."""
    from omegaconf.errors import OmegaConfBaseException

    message = user_message(err)
    if message is None:  # a bug: its traceback, and Hydra's hint
        traceback.print_exception(err)
        sys.stderr.write(
            os.linesep
            + "Set the environment variable HYDRA_FULL_ERROR=1 for a complete stack trace."
            + os.linesep
        )
        return
    if isinstance(err, SHORT_ERRORS) and isinstance(err.__cause__, OmegaConfBaseException):
        # OmegaConf's own message spans lines (full_key, object_type): its first says why.
        message = f"{message}: {str(err.__cause__).strip().splitlines()[0]}"
    sys.stderr.write(message + os.linesep)


# --- the decorator ----------------------------------------------------------------------------


def _hydra_flags(argv: list[str]) -> tuple[list[str], str | None]:
    """(overrides, --config-dir) of a Hydra command line."""
    from hydra._internal.utils import get_args_parser

    args, _ = get_args_parser().parse_known_args(argv)
    return list(args.overrides or []), args.config_dir


def _register_recipes(config_name: str, config_dir: str | None, overrides: list[str]) -> None:
    """The recipe options the defaults of ``config_name`` pick: each model's for ``train``;
    for ``prepare`` the dataset recipes, so that it prepares the dataset training reads."""
    from fusion_depth.config import recipes

    if config_name == "train":
        recipes.register_model_recipes(config_dir, overrides)
    elif config_name == "prepare":
        recipes.register_dataset_recipes(config_dir, overrides)


def hydra_main(config_name: str) -> Callable[[Callable[[DictConfig], Any]], Callable[[], Any]]:
    """``@hydra.main`` for the package's commands (see the module docstring for what it adds).

    Args:
        config_name: the primary config in ``conf/`` (``--config-name`` picks another, e.g. a
            sweep).
    """
    import hydra

    def decorate(task: Callable[[DictConfig], Any]) -> Callable[[], Any]:
        hydra_task = hydra.main(version_base="1.3", config_path=CONF_DIR, config_name=config_name)(
            _short_errors(task)
        )

        @functools.wraps(task)
        def main(cfg_passthrough: DictConfig | None = None) -> Any:
            if cfg_passthrough is not None:
                return hydra_task(cfg_passthrough)
            overrides, config_dir = _hydra_flags(sys.argv[1:])
            register_sweeps(config_dir)
            try:
                _register_recipes(config_name, config_dir, overrides)
            except UserError as err:  # a recipe file of one's own that cannot be read
                sys.stderr.write(f"{err}{os.linesep}")
                sys.exit(1)
            if os.environ.get("HYDRA_FULL_ERROR"):  # the user asked for Hydra's tracebacks
                return hydra_task()
            # Hydra then raises its errors instead of printing them, so that they are reported
            # here: an unknown key in one line, errors about the user's files short.
            global _reporting
            os.environ["HYDRA_FULL_ERROR"] = "1"
            _reporting = True
            try:
                return hydra_task()
            except KeyboardInterrupt:
                sys.stderr.write(f"fusion_depth.{config_name}: interrupted (Ctrl-C)" + os.linesep)
                sys.exit(130)
            except Exception as err:  # noqa: BLE001 - reported as Hydra would, only shorter
                unknown = unknown_key_message(err, overrides)
                if unknown is not None:
                    sys.stderr.write(unknown + os.linesep)
                else:
                    _report(err)
                sys.exit(1)
            finally:
                os.environ.pop("HYDRA_FULL_ERROR", None)
                _reporting = False
                if isinstance(sys.stderr, _WithoutJobLine):
                    sys.stderr = sys.stderr.stream

        return main

    return decorate
