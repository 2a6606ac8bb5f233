"""``python -m fusion_depth.score_sparse``: the sparse input scored as if it were the prediction.

A depth-completion model can only gain from its sparse input where that input is right. This
command scores a dataset split's sparse map against the ground truth on the pixels it covers
(a pixel counts where ``sparse > 0`` and the ground truth is scored by the ``eval`` protocol:
caps, crop, averaging, distance bins), and prints the test stage's tables (per condition, per
distance bin of the ground truth, per cap) with how much of the scored ground truth it covers.
For the built-in radar, whose returns are drawn as vertical lines
(``dataset.reader.radar_height_extension``), it shows how the lines agree with the surfaces they
are drawn over; docs/results/fusion-weather.md reads it.

python -m fusion_depth.score_sparse
python -m fusion_depth.score_sparse dataset.reader.radar_height_extension=0 split=val
python -m fusion_depth.score_sparse dataset=kitti dataset.root=/data/kitti
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from fusion_depth.config.hydra_main import hydra_main
from fusion_depth.data import SPLITS
from fusion_depth.runner.checkpoints import make_reader
from fusion_depth.runner.protocol import EvalProtocol, EvaluationResult, results_tables


@dataclass(frozen=True)
class SparseInputScore:
    """What :func:`score_sparse_input` measured.

    ``result`` scores the sparse map on the pixels it covers (its ``num_pixels`` count them);
    ``coverage`` is that count over the ground-truth pixels the protocol scores (a fraction in
    [0, 1], overall and per condition), ``num_frames`` the frames read.
    """

    result: EvaluationResult
    coverage: dict[str, float]
    num_frames: int


def sparse_at_points(
    sparse: torch.Tensor, points: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """A sparse map read at full-resolution ground-truth points, as the metrics take maps: each
    point gets the value of the map's pixel that holds it (nearest; interpolating would blend
    returns with the zeros around them), edges replicated.

    Shape:
        - sparse: (1, H, W) or (H, W) metres, 0 = no return.
        - points: (Q, 3) rows ``y, x, depth`` in the map's pixel coordinates (pixel centres at
          integers; depth 0: a padding row, never scored), a sample's ``depth_points``.
        - output: ``(sparse at the points, their depth)``, each (1, 1, 1, Q) metres.
    """
    height, width = sparse.shape[-2:]
    sparse = sparse.reshape(height, width)
    points = torch.as_tensor(points, dtype=torch.float32)
    rows = torch.floor(points[:, 0] + 0.5).long().clamp(0, height - 1)
    columns = torch.floor(points[:, 1] + 0.5).long().clamp(0, width - 1)
    return sparse[rows, columns].reshape(1, 1, 1, -1), points[:, 2].reshape(1, 1, 1, -1)


def score_sparse_input(
    dataset: Any, protocol: EvalProtocol, conditions: list[str] | None = None
) -> SparseInputScore:
    """Score each sample's ``sparse`` map (1×H×W metres, 0 = no return) against its ``depth``.

    Under ``eval.resolution=full`` (``eval=radarnet``) a sample that keeps its ground truth at
    the dataset's full resolution (``depth_points``: nuScenes' val and test) is scored there,
    as ``evaluate`` scores a prediction: each point against the map's pixel that holds it
    (:func:`sparse_at_points`); the result's protocol says ``resolution: network`` where no
    sample had them (the frames themselves were scored).

    Args:
        dataset: a split of any reader (samples as :class:`~fusion_depth.data.Sample`).
        protocol: how to score (:class:`~fusion_depth.runner.protocol.EvalProtocol`).
        conditions: the dataset's condition names, for the per-condition rows (None: none).

    Raises:
        ValueError: the sparse input covers no ground-truth pixel the protocol scores.
    """
    covered, every = protocol.scorer(conditions), protocol.scorer(conditions)
    scored_full = False
    for index in range(len(dataset)):
        sample = dataset[index]
        points = sample.get("depth_points") if protocol.resolution == "full" else None
        box = sample.get("frame_box")
        if points is not None:  # a box crops the frame's pixels, not the points
            sparse, depth = sparse_at_points(sample["sparse"], points)
            scored_full, box = True, None
        else:
            sparse, depth = sample["sparse"][None], sample["depth"][None]
        condition = [sample["condition"]] if conditions else None
        at = torch.tensor([index])
        box = None if box is None else torch.as_tensor(box)[None]
        # Ground truth where there is no return is 0, i.e. not scored (as a partial prediction).
        only_covered = torch.where(sparse > 0, depth, torch.zeros_like(depth))
        covered.update(sparse, only_covered, condition, index=at, frame_box=box)
        every.update(depth, depth, condition, index=at, frame_box=box)
    if protocol.resolution == "full" and not scored_full:
        protocol = replace(protocol, resolution="network")  # as evaluate records it
    try:
        result = EvaluationResult.from_metrics(protocol, covered, latency={})
    except ValueError:
        raise ValueError(
            f"the sparse input covers no ground-truth pixel in ({protocol.min_depth:g}, "
            f"{protocol.max_depth[-1]:g}) m in {len(dataset)} frames; nothing to score"
        ) from None
    totals = every.results()
    groups = {"all": (result.overall, totals["overall"])}
    groups.update(
        (name, (group, totals["by_condition"][name])) for name, group in result.by_condition.items()
    )
    coverage = {
        name: mine["num_pixels"] / all_["num_pixels"] for name, (mine, all_) in groups.items()
    }
    return SparseInputScore(result=result, coverage=coverage, num_frames=len(dataset))


def _resolution_note(asked: EvalProtocol, scored: EvalProtocol) -> str:
    """Where the ground truth was scored, for the command's first line."""
    if scored.resolution == "full":
        return "scored at the dataset's full resolution (eval.resolution=full), as evaluate does"
    if asked.resolution == "full":
        return (
            "scored at the frames' resolution: eval.resolution=full asks for the full "
            "resolution, and this split keeps no full-resolution ground truth (as evaluate)"
        )
    return "scored at the frames' resolution (eval.resolution=network)"


def score_sparse(cfg: DictConfig) -> SparseInputScore:
    """The command: read ``cfg.split`` of ``cfg.dataset``, score it, print the tables."""
    if cfg.split not in SPLITS:
        raise ValueError(f"split={cfg.split}: expected one of {', '.join(SPLITS)}")
    if cfg.dataset.sensor == "none":
        raise ValueError(f"dataset={cfg.dataset.name} has no sparse input (dataset.sensor: none)")
    block = OmegaConf.to_container(cfg.dataset, resolve=True)
    dataset = make_reader(block)(split=cfg.split)
    protocol = EvalProtocol.from_config(cfg.eval, cfg.dataset.min_depth, cfg.dataset.max_depth)
    conditions = list(cfg.dataset.get("conditions") or []) or None
    score = score_sparse_input(dataset, protocol, conditions)
    shares = ", ".join(f"{name} {100 * share:.2f} %" for name, share in score.coverage.items())
    print(
        f"dataset={cfg.dataset.name} split={cfg.split}: the sparse input ({cfg.dataset.sensor}) "
        f"scored as the prediction on the {score.result.overall['num_pixels']} ground-truth "
        f"pixels it covers in {score.num_frames} frames (coverage of the scored pixels: {shares})"
        f"; {_resolution_note(protocol, score.result.protocol)}"
    )
    print(results_tables(score.result))
    return score


@hydra_main("score_sparse")
def main(cfg: DictConfig) -> None:
    """Hydra entry point."""
    score_sparse(cfg)
