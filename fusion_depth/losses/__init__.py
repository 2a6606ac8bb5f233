"""Training losses on reciprocal depth (:mod:`.depth_loss`): SSIM + edge + a pixel term (L1, L2,
BerHu, log-L1), the paper's "Loss Functions", as functions and as the module
:class:`~.depth_loss.DepthLoss`."""
