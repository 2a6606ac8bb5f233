"""What every Hydra command line of the package shares (``train``, ``evaluate``, ``predict``,
``export``, ``prepare``; console scripts ``fusion-depth-<command>``):

* **Configs from anywhere.** The configs are read from :data:`~fusion_depth.config.CONF_DIR`
  (``conf/`` of a checkout, or the copy inside an installed package), and the sweep configs of
  ``sweeps/`` are registered by name in Hydra's config store, so ``--config-name
  procedural_weather`` finds them from any working directory (``--config-dir sweeps`` still
  works in a checkout, and picks your own sweep files first).
* **Paths as printed are paths as accepted.** Run folders are named after their overrides
  (``outputs/fusion=concat,loss=l1/``), and Hydra's override grammar reads ``=`` and ``,`` in an
  unquoted value as syntax. A path value that the grammar cannot read as typed (a path key such
  as ``ckpt_path``, ``input`` or ``hydra.run.dir``, or any value with a ``/``) is quoted for it,
  so it arrives exactly as typed (:func:`literal_paths`).
* **Unknown keys named before composing.** ``trainer.max_epoch=3`` gets the one-line
  ``did you mean max_epochs?`` error (with or without ``+``), not Hydra's struct error.
* **Short errors.** Errors the package raises about the user's data, config or files (a
  ``ValueError`` or ``OSError`` raised by package code, also from inside a DataLoader worker)
  print as their message, in a few lines, and so do Hydra's own errors about the user's files (a
  run folder it cannot create); ``HYDRA_FULL_ERROR=1`` shows the full traceback, as in Hydra.
"""

from __future__ import annotations

import functools
import os
import re
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.errors import CompactHydraException, ConfigCompositionException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError

from fusion_depth.config import CONF_DIR, SWEEPS_DIR, target_accepts, unknown_key_error
from fusion_depth.errors import CommandError, ConfigError

# Keys whose value is a file or folder (the last part of the key): their values are taken
# literally when Hydra's grammar cannot read them unquoted.
PATH_KEYS = frozenset(
    {
        "ckpt_path",
        "input",
        "sparse",
        "ground_truth",
        "output",
        "output_dir",
        "model_file",
        "root",
        "raw_root",
        "split_file",
        "weights",
        "dir",
        "subdir",
        "submitit_folder",
    }
)
# Folders Hydra creates for a run or a sweep: one folder, never a sweep over several.
RUN_DIR_KEYS = frozenset({"hydra.run.dir", "hydra.sweep.dir", "hydra.sweep.subdir"})
_PACKAGE_DIR = Path(__file__).resolve().parents[1]  # fusion_depth/


# --- paths as typed ---------------------------------------------------------------------------


def _quoted(value: str) -> str:
    """``value`` as a single-quoted Hydra string. Hydra reads a backslash as an escape only
    before a quote (and the closing one), so only those backslashes and the quotes are escaped."""
    escaped = re.sub(r"(\\*)'", lambda m: m[1] * 2 + "\\'", value)
    escaped = re.sub(r"(\\+)$", lambda m: m[1] * 2, escaped)
    return f"'{escaped}'"


def literal_paths(overrides: list[str]) -> list[str]:
    """The overrides with every path value the override grammar cannot read as typed quoted,
    so that it arrives unchanged: ``ckpt_path=outputs/fusion=concat/x.ckpt`` →
    ``ckpt_path='outputs/fusion=concat/x.ckpt'``. A value is a path when its key's last part is
    in :data:`PATH_KEYS` or it contains a ``/`` (or ``\\``). A value with a comma, which the
    grammar reads as a sweep, is one path after a path key when that path exists (``input=a,b``
    naming a folder ``a,b``), and always after :data:`RUN_DIR_KEYS`. Overrides the grammar reads
    otherwise (also quoted ones, interpolations, sweeps over paths) are left alone; ``${...}``
    in a value stays an interpolation, as in Hydra."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    out = []
    for override in overrides:
        key, sep, value = override.partition("=")
        name = key.lstrip("+~").rsplit(".", 1)[-1]
        if not sep or not (name in PATH_KEYS or "/" in value or "\\" in value):
            out.append(override)
            continue
        try:
            parsed = parser.parse_override(override)
            # A comma reads as a sweep: a path key's value is one path when that path exists,
            # and a run folder is never swept.
            literal = parsed.is_sweep_override() and (
                key.lstrip("+") in RUN_DIR_KEYS
                or (name in PATH_KEYS and Path(value).expanduser().exists())
            )
            if not literal:
                out.append(override)
                continue
        except Exception:  # noqa: BLE001 - any grammar error: try the quoted form
            pass
        quoted = f"{key}={_quoted(value)}"
        try:
            readable = parser.parse_override(quoted).value() == value
        except Exception:  # noqa: BLE001 - not a path the quoted form can carry either
            readable = False
        out.append(quoted if readable else override)
    return out


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


def _first_choices(overrides: list[Any]) -> list[str]:
    """The overrides as single values (a sweep's first choice), for one composition."""
    single = []
    for o in overrides:
        text = o.input_line
        if o.is_sweep_override():
            first = next(iter(o.sweep_string_iterator()))
            text = f"{o.get_key_element()}={first}"
        single.append(text)
    return single


def _missing_key_error(cfg: DictConfig, key: str, value: str) -> ConfigError:
    """The one-line error for ``key``, which ``cfg`` lacks: the first missing part is named,
    with the keys beside it (and ``+`` when the node's target accepts the key)."""
    parts = key.split(".")
    node: Any = cfg
    for i, part in enumerate(parts):
        if not isinstance(node, DictConfig) or part not in node:
            prefix = ".".join(parts[: i + 1])
            keys = node.keys() if isinstance(node, DictConfig) else []
            allowed = [str(k) for k in keys if not str(k).startswith("_")]
            if i == len(parts) - 1 and target_accepts(node, part):
                return ConfigError(
                    f"{key}: not in this config, but {node._target_} takes it: add it with "
                    f"+{key}={value}"
                )
            return unknown_key_error(prefix, allowed)
        node = node[part]
    return unknown_key_error(key, [])


def check_override_keys(
    config_name: str, overrides: list[str], config_dir: str | None = None
) -> None:
    """Raise a one-line ConfigError when an override sets a key the composed config lacks
    (Hydra's own message is a multi-line struct error). Anything else Hydra reports itself, so
    this returns quietly on every other composition problem."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
        single = _first_choices(parsed)
    except Exception:  # noqa: BLE001 - a grammar error, or an optimizer's interval: Hydra's
        return
    search = [f"hydra.searchpath=[file://{Path(config_dir).resolve()}]"] if config_dir else []
    if GlobalHydra.instance().is_initialized():  # e.g. inside a test's compose: not ours
        return

    def composed(with_overrides: list[str]) -> DictConfig:
        with initialize_config_dir(CONF_DIR, version_base="1.3"):
            return compose(
                config_name, overrides=[*with_overrides, *search], return_hydra_config=True
            )

    try:
        composed(single)
        return
    except ConfigCompositionException as err:
        if not isinstance(err.__cause__, ConfigAttributeError | ConfigKeyError):
            return
        # Hydra's message names the override: "Could not override 'trainer.max_epoch'."
        failing = next((o for o in parsed if f"'{o.key_or_group}'" in str(err)), None)
    except Exception:  # noqa: BLE001 - e.g. a bad group choice: Hydra names its options
        return
    if failing is None or failing.is_add() or failing.is_delete():
        return
    rest = [s for o, s in zip(parsed, single, strict=True) if o is not failing]
    try:
        cfg = composed(rest)
    except Exception:  # noqa: BLE001 - cannot say more than Hydra would
        return
    value = failing.input_line.partition("=")[2]
    raise _missing_key_error(cfg, failing.key_or_group, value)


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


def user_message(err: BaseException) -> str | None:
    """The message to show instead of a traceback for an error about the user's input (data,
    config values, files), or None for anything else (a bug keeps its traceback)."""
    text = str(err).strip()
    if _study_without_completed_trial(err):
        return (
            "hparams_search: no trial of the study completed, so it has no best configuration; "
            "each failed trial's error is above and in its run folder's failure.json"
        )
    if isinstance(err, CompactHydraException):
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


def _short_errors(task: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    @functools.wraps(task)  # keeps the module and name Hydra derives the job name from
    def run(cfg: DictConfig) -> Any:
        try:
            return task(cfg)
        except CompactHydraException as err:
            message = user_message(err)
            if message != str(err).strip():
                raise CommandError(message) from err
            raise
        except (OSError, ValueError) as err:
            message = user_message(err)
            if message is None:
                raise
            raise CommandError(message) from err

    return run


def _report(err: Exception) -> None:
    """Print ``err`` as Hydra does without ``HYDRA_FULL_ERROR``, but an error about the user's
    input (:func:`user_message`) as its message alone."""
    from omegaconf.errors import OmegaConfBaseException

    message = user_message(err)
    if message is None:
        traceback.print_exception(err)
    else:
        sys.stderr.write(message + os.linesep)
        if isinstance(err, CompactHydraException) and isinstance(
            err.__cause__, OmegaConfBaseException
        ):
            sys.stderr.write(str(err.__cause__) + os.linesep)
    sys.stderr.write(
        os.linesep
        + "Set the environment variable HYDRA_FULL_ERROR=1 for a complete stack trace."
        + os.linesep
    )


# --- the decorator ----------------------------------------------------------------------------


def _hydra_flags(argv: list[str]) -> tuple[list[str], str | None, str | None]:
    """(overrides, --config-dir, --config-name) of a Hydra command line."""
    from hydra._internal.utils import get_args_parser

    args, _ = get_args_parser().parse_known_args(argv)
    return list(args.overrides or []), args.config_dir, args.config_name


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
            overrides, config_dir, chosen = _hydra_flags(sys.argv[1:])
            register_sweeps(config_dir)
            typed = literal_paths(overrides)
            if typed != overrides:
                rewrite = dict(zip(overrides, typed, strict=True))
                sys.argv = [sys.argv[0], *(rewrite.get(a, a) for a in sys.argv[1:])]
            if os.environ.get("HYDRA_FULL_ERROR"):  # the user asked for Hydra's tracebacks
                return hydra_task()
            try:
                check_override_keys(chosen or config_name, typed, config_dir)
            except ConfigError as err:
                sys.stderr.write(f"{err}\n")
                sys.exit(1)
            # Errors then come back here instead of being printed by Hydra, so that those Hydra
            # raises itself about the user's files (a run folder it cannot create) are short too.
            os.environ["HYDRA_FULL_ERROR"] = "1"
            try:
                return hydra_task()
            except Exception as err:  # noqa: BLE001 - reported as Hydra would, only shorter
                _report(err)
                sys.exit(1)
            finally:
                os.environ.pop("HYDRA_FULL_ERROR", None)

        return main

    return decorate
