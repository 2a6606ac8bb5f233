"""``report RUN --panels OUT.png``: a run's test panels drawn again from its record.

A run writes its test panels twice: ``test_panels.png`` and the frames behind it as arrays,
``test_panels.npz`` (:func:`fusion_depth.data.visualize.write_panel_frames`). From a copy of the
arrays under ``results/records/`` the figure is drawn again with no checkpoint, so the docs'
pictures are made by a command, like their tables, and a test makes them again.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from PIL import Image
from PIL.PngImagePlugin import PngInfo

from fusion_depth.data.visualize import panel_figure, read_panel_frames
from fusion_depth.report.output import check_target, naming_a_full_disk
from fusion_depth.runner.run_folder import TEST_PANEL_FRAMES_FILE
from fusion_depth.utils.atomic import write_atomic


def recorded_panel_frames(directory: str | os.PathLike) -> Path:
    """The one ``test_panels.npz`` at or below ``directory``.

    Raises:
        ValueError: none, or several (naming two of them: pick a run's folder).
    """
    found = sorted(Path(directory).rglob(TEST_PANEL_FRAMES_FILE))
    if not found:
        raise ValueError(f"{directory}: no {TEST_PANEL_FRAMES_FILE} found below it")
    if len(found) > 1:
        raise ValueError(
            f"{directory}: {len(found)} runs recorded panels ({found[0]}, {found[1]}, ...); "
            "name one run's folder"
        )
    return found[0]


def _drawn_by_panels(path: Path) -> bool:
    """Whether ``path`` is a PNG :func:`draw_recorded_panels` wrote (its description names the
    frames it was drawn from)."""
    try:
        with Image.open(path) as image:
            described = json.loads(image.info.get("Description", ""))
    except (OSError, ValueError):
        return False
    return isinstance(described, dict) and "frames" in described


def draw_recorded_panels(
    directory: str | os.PathLike, out: str | os.PathLike, command: str
) -> Path:
    """The panel figure (:func:`fusion_depth.data.visualize.panel_figure`) of the one run
    recorded at or below ``directory``, written atomically to ``out`` as a PNG whose
    ``Description`` text chunk holds ``{"command": command, "frames": <the .npz's path>,
    "matplotlib": <its version>}``.

    Drawing the same record again on the same Matplotlib (which draws the labels) gives the
    same pixels.

    Raises:
        ValueError: ``out`` is not a ``.png``, or is a file report may not replace (a run's
            record, a folder, a PNG this command did not draw: :func:`check_target`); no single
            record; the record is not a panel-frames file, holds no frame, has a depth range
            that cannot be drawn, or would make a figure beyond the limits of
            :func:`~fusion_depth.data.visualize.read_panel_frames` (checked before any array
            is read).
        OSError: reading or writing failed; a full disk names ``out``.
    """
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise ValueError(f"--panels {out}: expected a file name ending in .png")
    check_target(out, "--panels", _drawn_by_panels)
    frames_file = recorded_panel_frames(directory)
    frames, min_depth, max_depth = read_panel_frames(frames_file)
    figure = panel_figure(frames, min_depth, max_depth)
    from matplotlib import __version__ as matplotlib_version  # it draws the labels

    described = {
        "command": command,
        "frames": frames_file.as_posix(),
        "matplotlib": matplotlib_version,
    }
    info = PngInfo()
    info.add_text("Description", json.dumps(described))

    def write(tmp: Path) -> None:
        Image.fromarray(figure, "RGB").save(tmp, format="PNG", pnginfo=info)

    with naming_a_full_disk(out):
        write_atomic(out, write, suffix=".png")
    return out
