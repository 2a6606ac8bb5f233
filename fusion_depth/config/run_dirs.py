"""Run and sweep folder names (``conf/hydra/default.yaml``): named after the run's overrides, so
the same command finds the same folder again.

A name uses only characters that Hydra's override grammar and a shell read as plain text
(letters, digits, ``_ . - + @ %``): ``fusion=concat,loss=l1`` names the folder
``fusion-concat+loss-l1``, and a path printed by a run (``outputs/fusion-concat+loss-l1/...``)
can be pasted into any command unquoted. Folders of releases before 0.2 were named with ``=``
and ``,`` (:func:`legacy_run_dirname`); a run whose folder of that name exists, and whose new
name does not, keeps using it, so re-running an old command still resumes or skips it.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

_MAX_DIRNAME = 200  # bytes; file systems allow 255
# Everything outside what the override grammar reads unquoted and a shell passes as is.
_NOT_PLAIN = re.compile(r"[^A-Za-z0-9_.+@%-]")


def _shortened(name: str) -> str:
    """``name`` cut to :data:`_MAX_DIRNAME` bytes, ending in a hash of the whole when cut."""
    if len(name.encode()) <= _MAX_DIRNAME:
        return name
    digest = hashlib.sha1(name.encode()).hexdigest()[:10]
    return f"{name.encode()[: _MAX_DIRNAME - 11].decode(errors='ignore')}-{digest}"


def run_dirname(override_dirname: str) -> str:
    """A run's folder name from Hydra's ``override_dirname`` (``fusion=concat,loss=l1``).

    ``=`` becomes ``-`` and ``,`` becomes ``+`` (``fusion-concat+loss-l1``); any other
    character the override grammar or a shell would read as syntax (``/``, spaces, quotes,
    brackets, ``:``, ``$``, ...) becomes ``_``. ``default`` when there are no overrides; a name
    over 200 bytes is cut and ends in a hash of the whole. Two runs whose overrides map to one
    name cannot mix: a run only resumes a checkpoint of its own configuration
    (:func:`fusion_depth.runner.resume.plan_start`).
    """
    name = _NOT_PLAIN.sub("_", override_dirname.replace("=", "-").replace(",", "+"))
    return _shortened(name or "default")


def legacy_run_dirname(override_dirname: str) -> str:
    """The folder name releases before 0.2 gave the same run: ``override_dirname`` as it is
    (``fusion=concat,loss=l1``), with ``/`` as ``_``."""
    return _shortened(override_dirname.replace(os.sep, "_") or "default")


def _found_name(parent: str | os.PathLike, override_dirname: str) -> str:
    """The folder name of ``override_dirname`` inside ``parent``: :func:`run_dirname`, or
    :func:`legacy_run_dirname` when only a folder of that name exists there."""
    name, legacy = run_dirname(override_dirname), legacy_run_dirname(override_dirname)
    if legacy != name and (Path(parent) / legacy).is_dir() and not (Path(parent) / name).exists():
        return legacy
    return name


def run_dir(parent: str, override_dirname: str) -> str:
    """``parent/<run_dirname>`` (``hydra.run.dir``), or the folder an earlier release named
    after the same overrides when only that one exists."""
    return f"{parent}/{_found_name(parent, override_dirname)}"


def job_subdir(sweep_dir: str, override_dirname: str) -> str:
    """A sweep job's folder name inside ``sweep_dir`` (``hydra.sweep.subdir``), or the one an
    earlier release gave the same job when only that one exists."""
    return _found_name(sweep_dir, override_dirname)


def sweep_dir(parent: str, config_name: str, override_dirname: str) -> str:
    """A sweep's folder (``hydra.sweep.dir``): ``parent``, then the sweep config's name
    (``--config-name``, unless it is ``train``), then the sweep's own overrides, e.g.
    ``multirun/loss-l1+l2+berhu``; the folder an earlier release named after the same sweep
    when only that one exists.

    Registered with ``use_cache``: OmegaConf caches by the interpolation's text, and Hydra
    copies the sweep's cache into every job's config, so all jobs share the sweep's folder
    although each job's ``override_dirname`` is its own.
    """
    named = parent
    if config_name not in ("", "None", "train"):
        named = f"{parent}/{config_name}"
    elif not override_dirname:
        return f"{parent}/default"
    if not override_dirname:
        return named
    return f"{named}/{_found_name(named, override_dirname)}"
