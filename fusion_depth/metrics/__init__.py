"""Depth evaluation metrics (:mod:`.depth`: the paper's ARD, SRD, RMSE and δ, plus the KITTI set,
as functions and as the torchmetrics-style :class:`~.depth.DepthMetrics`) and the uncertainty of
a paired comparison between two models (:mod:`.bootstrap`)."""
