"""Run and sweep folder names (``conf/hydra/default.yaml``): named after the run's overrides, so
the same command finds the same folder again.
"""

from __future__ import annotations

import hashlib
import os

_MAX_DIRNAME = 200  # bytes; file systems allow 255


def run_dirname(override_dirname: str) -> str:
    """A folder name for a run from Hydra's ``override_dirname`` (``fusion=concat,loss=l1``):
    the same overrides give the same folder, so re-running a command finds its run again.
    ``default`` when there are none; ``/`` in values becomes ``_``; overly long names are cut
    and end in a hash of the whole."""
    name = override_dirname.replace(os.sep, "_") or "default"
    if len(name.encode()) > _MAX_DIRNAME:
        digest = hashlib.sha1(name.encode()).hexdigest()[:10]
        name = f"{name.encode()[: _MAX_DIRNAME - 11].decode(errors='ignore')}-{digest}"
    return name


def sweep_dirname(config_name: str, override_dirname: str) -> str:
    """A sweep's folder: the sweep config's name (``--config-name``, unless it is ``train``)
    and the sweep's own overrides, e.g. ``loss=l1,l2,berhu``.

    Registered with ``use_cache``: OmegaConf caches by the interpolation's text, and Hydra
    copies the sweep's cache into every job's config, so all jobs share the sweep's folder
    although each job's ``override_dirname`` is its own.
    """
    parts = [config_name] if config_name not in ("", "None", "train") else []
    if override_dirname or not parts:
        parts.append(run_dirname(override_dirname))
    return "/".join(parts)
