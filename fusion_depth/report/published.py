"""Published numbers beside the user's: ``python -m fusion_depth.report <folder> --published``.

:data:`PUBLISHED` holds, for each released model the platform runs
(:data:`fusion_depth.models.released.RELEASED`), the numbers its paper prints: MAE and RMSE in
mm per depth cap, with the paper and table they come from. A record of that model scored under
the same protocol (``eval=radarnet``) on the same dataset gets a row per cap: its score, the
published one and the difference (ours − published, so negative is lower error).

``checked`` says whether each value was read off the paper's table by whoever added it. A
value that was not (typed from a secondary source, or from memory where the paper could not
be opened) is printed with the table's note "unchecked", so nobody cites it as the paper's
without looking. To add or correct one, edit this table: it is the only place they live.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from fusion_depth.metrics.depth import metric_in_units
from fusion_depth.models.released import released_entry
from fusion_depth.runner.record import RunRecord
from fusion_depth.utils.tables import format_table

PUBLISHED_METRICS = ("mae", "rmse")


@dataclass(frozen=True)
class PublishedScores:
    """What a paper prints for one method under one protocol.

    Attributes:
        model: the record's model (:func:`~fusion_depth.models.released.record_model_name`).
        datasets: the dataset names its records may carry (``nuscenes``, ``radarnet_layout``:
            the same frames).
        preset: the ``eval`` preset it was scored under.
        source: the paper and table.
        caps: cap in metres (as ``test_by_cap`` names it) → (MAE, RMSE) in mm.
        checked: whether the values were read off ``source`` itself.
    """

    model: str
    datasets: tuple[str, ...]
    preset: str
    source: str
    caps: Mapping[str, tuple[float, float]]
    checked: bool


PUBLISHED: tuple[PublishedScores, ...] = (
    PublishedScores(
        model="radarnet_released",
        datasets=("nuscenes", "radarnet_layout"),
        preset="radarnet",
        source="Singh et al., CVPR 2023, Table 1 (nuScenes test, 80 m)",
        # Only the 80 m row: the 50 and 70 m rows were not at hand when this was written.
        caps={"80": (2179.3, 4898.7)},
        checked=False,
    ),
)


def published_for(run: RunRecord) -> PublishedScores | None:
    """The published scores a record can be put beside: same model, dataset and preset."""
    identity = run.run
    preset = (run.protocol or {}).get("preset")
    for scores in PUBLISHED:
        if (
            identity is not None
            and identity.model == scores.model
            and identity.dataset in scores.datasets
            and preset == scores.preset
        ):
            return scores
    return None


def _cells(mine: float, theirs: float) -> list[str]:
    return [f"{mine:.1f}", f"{theirs:.1f}", f"{mine - theirs:+.1f}"]


def build_published_table(runs: Sequence[RunRecord], fmt: str = "markdown") -> str:
    """A row per (record, cap) with a published counterpart: MAE and RMSE (mm), ours,
    published and the difference, and the source; a note names unchecked values.

    Raises:
        ValueError: no record has published numbers to be put beside (naming what the records
            hold and what is published).
    """
    header = ["Method", "Cap (m)", "Images"]
    for metric in PUBLISHED_METRICS:
        name = metric.upper()
        header += [f"{name} (mm)", f"{name} published", f"Δ{name}"]
    header.append("Source")
    rows, unchecked = [], False
    for run in runs:
        scores = published_for(run)
        if scores is None:
            continue
        entry = released_entry(scores.model)
        for cap, published in scores.caps.items():
            section = (run.test_by_cap or {}).get(cap)
            if section is None:
                continue
            row = [entry.label if entry else scores.model, cap, str(section["num_images"])]
            for metric, theirs in zip(PUBLISHED_METRICS, published, strict=True):
                row += _cells(metric_in_units(metric, section[metric], "mm"), theirs)
            row.append(scores.source + ("" if scores.checked else " (unchecked)"))
            rows.append(row)
            unchecked |= not scores.checked
    if not rows:
        held = sorted({f"{r.run.model} on {r.run.dataset}" for r in runs if r.run is not None})
        known = [f"{s.model} on {'/'.join(s.datasets)}, eval={s.preset}" for s in PUBLISHED]
        raise ValueError(
            f"--published: no record below has published numbers to compare with (the records "
            f"hold {', '.join(held) or 'no run identity'}; published: {'; '.join(known)})"
        )
    table = format_table(header, rows, fmt)
    if unchecked and fmt == "markdown":
        table += (
            "\n\n(unchecked): typed without the paper at hand; check the value against the "
            "table named before citing it (fusion_depth/report/published.py)"
        )
    return table
