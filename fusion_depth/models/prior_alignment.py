"""The global alignment of a frozen prior, scored as a network with nothing learned: the first
stage of RadarCam-Depth (Li et al., ICRA 2024, Sec. III-B) and SA-RCD, and POLAR's (CVPR 2026)
affine baseline: each frame's relative inverse depth scaled and shifted to its own sparse
returns (a metric prior's depth scaled), by RANSAC over the returns and a least-squares refit
(:func:`~fusion_depth.models.alignment.fit_scale_shift`).

``python -m fusion_depth.evaluate prior=<name> prior.weights=<file> dataset=<name>`` scores it
(:mod:`fusion_depth.evaluate.scoring`); ``alignment.*`` sets the fit.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from fusion_depth.errors import ArgumentError
from fusion_depth.models.alignment import (
    DEFAULT_RANSAC_ITERATIONS,
    DEFAULT_RANSAC_THRESHOLD,
    FallbackCount,
    apply_alignment,
    check_alignment_arguments,
    fit_scale_shift,
    prior_kind,
)
from fusion_depth.models.base import DepthModel
from fusion_depth.models.depth_prior import NO_PRIOR, build_prior
from fusion_depth.models.fusion import InputMode

MODEL_NAME = "prior_alignment"  # model.net.name in its records
LABEL = "Prior + alignment"  # how report's tables name it


class GlobalAlignment(FallbackCount, DepthModel):
    """A frozen prior made metric frame by frame by the frame's sparse returns.

    What is fitted follows the prior's ``kind``: a relative prior's scale and shift in inverse
    depth, a metric prior's scale in metres. Given the batch's ``radar_points``, each return is
    one sample of the fit; without them (lidar), each pixel with a return. A frame without a
    fit of its own (too few returns, or none that keeps the depth order) takes its batch's
    median fit, or, in a batch with none, the mean of the batches' median fits so far
    (:class:`FallbackCount` counts them, and those whose fits all reversed the depth order);
    the first batches of a run, before any fit, take scale 1 and shift 0.

    Args:
        prior: the ``prior`` config node (``name``, ``weights``, ``input_size``, ``kind``,
            ``max_depth``; ``dropout`` and ``cache`` are ignored). Required: ``name`` is not
            ``none``.
        ransac_iterations: N > 0: RANSAC with N minimal samples (the default, 100); 0: least
            squares on every return.
        ransac_threshold: RANSAC's inlier bound, a relative error (of inverse depth for a
            relative prior, of depth for a metric one).
        min_depth: the depth range's lower end in metres.
        max_depth: its upper end in metres.

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1]; sparse: (B, 1, H, W) metres, 0 = no return;
          points: (B, P, 6) ``radar_points`` or None; prior: (B, 1, H, W) the prior's output
          where the frame brings it (``prior=oracle``), else None: the prior runs.
        - output: (B, 1, H, W) metres in ``[min_depth, max_depth]`` (its output space is
          depth).

    Raises:
        ArgumentError: ``prior.name`` is ``none``, the prior cannot be built, or an alignment
            setting is out of range (naming it).
    """

    output_space = "depth"
    takes_points = True  # one sample per radar return where the batch has them

    def __init__(
        self,
        prior: Mapping[str, Any],
        ransac_iterations: int = DEFAULT_RANSAC_ITERATIONS,
        ransac_threshold: float = DEFAULT_RANSAC_THRESHOLD,
        min_depth: float = 0.5,
        max_depth: float = 80.0,
    ) -> None:
        super().__init__(min_depth, max_depth, depth_scale=1.0)
        # What builds the prior; dropout and cache are a trained network's and the runner's.
        spec = {k: v for k, v in prior.items() if k not in ("dropout", "cache", "enabled")}
        if spec["name"] in (None, NO_PRIOR):
            raise ArgumentError(
                f"{{name}}={spec['name']}: the global alignment needs a prior "
                "(prior=depth_anything_v2 or prior=checkpoint)",
                "name",
                owner=build_prior,
            )
        check_alignment_arguments(ransac_iterations, ransac_threshold)  # evaluate's alignment.*
        self.prior = build_prior(**spec)
        self.kind = prior_kind(self.prior)
        self.ransac_iterations, self.ransac_threshold = ransac_iterations, ransac_threshold
        self.fusion = InputMode("concat", uses_sparse=True)  # image and sparse returns in
        # (scale, shift) of the batches before: the fit of a batch with no frame to fit
        self.register_buffer("fit_mean", torch.tensor([1.0, 0.0], dtype=torch.float64))
        self.fitted_batches = 0
        self.reset_fits()

    def forward(
        self,
        image: torch.Tensor,
        sparse: torch.Tensor | None = None,
        points: torch.Tensor | None = None,
        prior: torch.Tensor | None = None,
    ) -> torch.Tensor:
        if sparse is None:
            raise ValueError("the global alignment needs the sparse depth map")
        # The prior as it gives it, or as the frame brings it (prior=oracle: its ground truth).
        given = (self.prior(image) if prior is None else prior).float()
        # In float64 whatever the autocast (fit_scale_shift): bf16 moves a shift by 10 %.
        with torch.autocast(image.device.type, enabled=False):
            fit = fit_scale_shift(
                given,
                sparse.float(),
                self.kind,
                self.ransac_iterations,
                self.ransac_threshold,
                fallback=tuple(self.fit_mean.tolist()),
                points=points,
            )
            self._remember(fit.scale[~fit.fallback], fit.shift[~fit.fallback])
            self.count_fits(fit)
            return apply_alignment(given, fit, self.kind, self.min_depth, self.max_depth)

    def fit_summary(self) -> dict[str, Any]:
        """The fit's settings, and its fits and fallbacks since :meth:`reset_fits`."""
        settings = {"kind": self.kind, "ransac_iterations": self.ransac_iterations}
        return {**settings, **super().fit_summary()}

    def _remember(self, scale: torch.Tensor, shift: torch.Tensor) -> None:
        """Fold a batch's median fit into the running mean of the batches' medians."""
        if len(scale) == 0:
            return
        self.fitted_batches += 1
        batch = torch.stack([scale.median(), shift.median()]).to(self.fit_mean)
        self.fit_mean += (batch - self.fit_mean) / self.fitted_batches


def prior_alignment_config(prior: Mapping[str, Any], alignment: Mapping[str, Any]) -> dict:
    """``model.net`` of a global alignment's record: its name, prior and fit settings."""
    return {"name": MODEL_NAME, "prior": dict(prior), **dict(alignment)}
