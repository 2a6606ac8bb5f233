"""Run and sweep folder names (``conf/hydra/default.yaml``): named after the run's overrides, so
the same command finds the same folder again.

A name uses only characters that Hydra's override grammar and a shell read as plain text
(letters, digits, ``_ . - + @ %``): ``fusion=concat,loss=l1`` names the folder
``fusion-concat+loss-l1``, and a path printed by a run (``outputs/fusion-concat+loss-l1/...``)
can be pasted into any command unquoted. Folders of releases before 0.2 were named with ``=``
and ``,`` (:func:`legacy_run_dirname`); a run whose folder of that name exists, and whose new
name does not, keeps using it, so re-running an old command still resumes or skips it.

A prior's weights (``prior.weights=/home/me/weights/da2-small``) are named by the file or
folder's own name and a digest of its absolute path (``prior.weights-da2-small-1a2b3c4d``), not
by the whole path; folders named with the whole path (before 0.3) are found as legacy names are.
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


# ``prior.weights=<path>`` (or ``model.net.prior.weights``) in an ``override_dirname``: its value
# runs to the next ``,<key>=`` (a sweep's value holds commas itself) or the end.
_WEIGHTS = re.compile(
    r"(?:^|(?<=,))([+~]*(?:model\.net\.)?prior\.weights)=(.*?)(?=,[+~]*[A-Za-z_][\w.@/-]*=|$)"
)
_WEIGHTS_DIGEST = 8  # hex digits of the path's digest


def _weights_name(value: str) -> str:
    """A weights path as a folder name: its own name and a digest of its absolute path
    (``/home/me/weights/da2-small`` → ``da2-small-<8 hex digits>``)."""
    path = value.strip().strip("'\"")
    if path in ("", "null", "None"):
        return value
    absolute = os.path.abspath(os.path.expanduser(path))
    digest = hashlib.sha256(absolute.encode()).hexdigest()[:_WEIGHTS_DIGEST]
    return f"{Path(absolute).name or 'root'}-{digest}"


def _short_weights(override_dirname: str) -> str:
    """``override_dirname`` with each ``prior.weights`` path (each of a sweep's) shortened by
    :func:`_weights_name`."""

    def shorten(match: re.Match) -> str:
        values = ",".join(_weights_name(v) for v in match.group(2).split(","))
        return f"{match.group(1)}={values}"

    return _WEIGHTS.sub(shorten, override_dirname)


def _plain_name(override_dirname: str) -> str:
    name = _NOT_PLAIN.sub("_", override_dirname.replace("=", "-").replace(",", "+"))
    return _shortened(name or "default")


def run_dirname(override_dirname: str) -> str:
    """A run's folder name from Hydra's ``override_dirname`` (``fusion=concat,loss=l1``).

    ``=`` becomes ``-`` and ``,`` becomes ``+`` (``fusion-concat+loss-l1``); any other
    character the override grammar or a shell would read as syntax (``/``, spaces, quotes,
    brackets, ``:``, ``$``, ...) becomes ``_``. A ``prior.weights`` path is named by its own
    name and 8 hex digits of a SHA-256 of its absolute path
    (``prior.weights-da2-small-1a2b3c4d``): short, the same for the same path, another for
    another path. ``default`` when there are no overrides; a name over 200 bytes is cut and
    ends in a hash of the whole. Two runs whose overrides map to one name cannot mix: a run
    only resumes a checkpoint of its own configuration
    (:func:`fusion_depth.runner.resume.plan_start`).
    """
    return _plain_name(_short_weights(override_dirname))


def legacy_run_dirname(override_dirname: str) -> str:
    """The folder name releases before 0.2 gave the same run: ``override_dirname`` as it is
    (``fusion=concat,loss=l1``), with ``/`` as ``_``."""
    return _shortened(override_dirname.replace(os.sep, "_") or "default")


def _found_name(parent: str | os.PathLike, override_dirname: str) -> str:
    """The folder name of ``override_dirname`` inside ``parent``: :func:`run_dirname`, or an
    earlier release's name for it when only a folder of that name exists there (weights paths
    spelt out, then :func:`legacy_run_dirname`)."""
    name = run_dirname(override_dirname)
    if (Path(parent) / name).exists():
        return name
    for earlier in (_plain_name(override_dirname), legacy_run_dirname(override_dirname)):
        if earlier != name and (Path(parent) / earlier).is_dir():
            return earlier
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
