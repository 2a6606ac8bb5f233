"""The global alignment of a frozen prior, scored as a network with nothing learned: the first
stage of RadarCam-Depth (Li et al., ICRA 2024) and SA-RCD, and POLAR's (CVPR 2026) affine
baseline: each frame's relative inverse depth scaled and shifted to its own sparse returns by
least squares (:func:`~fusion_depth.models.alignment.fit_scale_shift`).

``python -m fusion_depth.evaluate prior=<name> prior.weights=<file> dataset=<name>`` scores it
(:mod:`fusion_depth.evaluate.scoring`); ``alignment.*`` sets the fit.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from fusion_depth.errors import ArgumentError
from fusion_depth.models.alignment import (
    FallbackCount,
    apply_alignment,
    check_alignment_arguments,
    fit_scale_shift,
)
from fusion_depth.models.base import DepthModel
from fusion_depth.models.depth_prior import NO_PRIOR, build_prior
from fusion_depth.models.fusion import InputMode

MODEL_NAME = "prior_alignment"  # model.net.name in its records
LABEL = "Prior + alignment"  # how report's tables name it


class GlobalAlignment(FallbackCount, DepthModel):
    """A frozen prior made metric frame by frame by the frame's sparse returns.

    A frame with fewer than two returns to fit takes its batch's median fit, or, in a batch
    with none, the mean of the batches' median fits so far (:class:`FallbackCount` counts
    them); the first batches of a run, before any fit, take scale 1 and shift 0.

    Args:
        prior: the ``prior`` config node (``name``, ``weights``, ``input_size``; ``dropout`` is
            ignored). Required: ``name`` is not ``none``.
        space: fit in ``inverse`` depth or in ``depth``
            (:func:`~fusion_depth.models.alignment.fit_scale_shift`).
        ransac_iterations: 0 fits every return; N > 0: RANSAC with N two-point samples.
        ransac_threshold: RANSAC's inlier bound, a relative error in the fitted space.
        min_depth: the depth range's lower end in metres.
        max_depth: its upper end in metres.

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1]; sparse: (B, 1, H, W) metres, 0 = no return.
        - output: (B, 1, H, W) metres in ``[min_depth, max_depth]`` (its output space is
          depth).

    Raises:
        ArgumentError: ``prior.name`` is ``none``, the prior cannot be built, or an alignment
            setting is out of range (naming it).
    """

    output_space = "depth"

    def __init__(
        self,
        prior: Mapping[str, Any],
        space: str = "inverse",
        ransac_iterations: int = 0,
        ransac_threshold: float = 0.1,
        min_depth: float = 0.5,
        max_depth: float = 80.0,
    ) -> None:
        super().__init__(min_depth, max_depth, depth_scale=1.0)
        spec = {key: prior.get(key) for key in ("name", "weights", "input_size")}
        if spec["name"] in (None, NO_PRIOR):
            raise ArgumentError(
                f"{{name}}={spec['name']}: the global alignment needs a prior "
                "(prior=depth_anything_v2 or prior=checkpoint)",
                "name",
                owner=build_prior,
            )
        check_alignment_arguments(space, ransac_iterations, ransac_threshold)
        self.prior = build_prior(**spec)
        self.space = space
        self.ransac_iterations, self.ransac_threshold = ransac_iterations, ransac_threshold
        self.fusion = InputMode("concat", uses_sparse=True)  # image and sparse returns in
        # (scale, shift) of the batches before: the fit of a batch with no frame to fit
        self.register_buffer("fit_mean", torch.tensor([1.0, 0.0], dtype=torch.float64))
        self.fitted_batches = 0
        self.reset_fits()

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        if sparse is None:
            raise ValueError("the global alignment needs the sparse depth map")
        # The prior as it gives it: the depth space's fit takes its reciprocal, so no shift
        # may be added to it (it is never read from the cache, which normalises).
        relative = self.prior(image).float()
        # In float64 whatever the autocast (fit_scale_shift): bf16 moves a shift by 10 %.
        with torch.autocast(image.device.type, enabled=False):
            fit = fit_scale_shift(
                relative,
                sparse.float(),
                self.space,
                self.ransac_iterations,
                self.ransac_threshold,
                fallback=tuple(self.fit_mean.tolist()),
            )
            self._remember(fit.scale[~fit.fallback], fit.shift[~fit.fallback])
            self.count_fits(fit.fallback)
            return apply_alignment(relative, fit, self.space, self.min_depth, self.max_depth)

    def fit_summary(self) -> dict[str, Any]:
        """The fit's settings, and its fits and fallbacks since :meth:`reset_fits`."""
        settings = {"space": self.space, "ransac_iterations": self.ransac_iterations}
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
