"""The prior as its own input branch (fusion_depth.models.prior_branch): never mixed into the
image encoder's input, the network without a prior at the start, and a path the prior's
gradient and information take once trained."""

from __future__ import annotations

import pytest
import torch
from helpers.prior import KnownPrior, tiny_depth_anything

from fusion_depth.models import DepthNet
from fusion_depth.models.prior_branch import PriorBranch


@pytest.fixture(scope="module")
def tiny_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_depth_anything")
    tiny_depth_anything().save_pretrained(folder)
    return folder


def _pair(tiny_folder):
    spec = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    torch.manual_seed(0)
    with_prior = DepthNet("resnet10t", "concat", prior=spec).eval()
    torch.manual_seed(0)
    without = DepthNet("resnet10t", "concat").eval()
    without.load_state_dict(with_prior.state_dict(), strict=False)
    return with_prior, without


def test_at_the_start_the_network_is_the_one_without_a_prior(tiny_folder):
    with_prior, without = _pair(tiny_folder)
    image, sparse = torch.rand(2, 3, 64, 96), torch.rand(2, 1, 64, 96) * 40
    depth = 2.0 + 30.0 * torch.rand(2, 1, 64, 96)
    with_prior.prior = KnownPrior(depth)
    torch.testing.assert_close(with_prior(image, sparse), without(image, sparse))
    # Its own branch: the image encoder's input has no prior channel mixed in.
    assert not any("prior" in name for name, _ in with_prior.fusion.named_parameters())
    assert with_prior.prior_branch is not None and without.prior_branch is None


def test_once_trained_the_prior_changes_the_output_through_the_branch(tiny_folder):
    with_prior, _ = _pair(tiny_folder)
    image, sparse = torch.rand(2, 3, 64, 96), torch.rand(2, 1, 64, 96) * 40
    near = 2.0 + 30.0 * torch.rand(2, 1, 64, 96)
    with_prior.train()
    with_prior.prior_dropout = 0.0
    with_prior.prior = KnownPrior(near)
    loss = with_prior(image, sparse).mean()
    loss.backward()
    grads = [p.grad for p in with_prior.prior_branch.projections.parameters()]
    assert all(g is not None and g.abs().sum() > 0 for g in grads)  # the zero convs learn
    with torch.no_grad():
        for projection in with_prior.prior_branch.projections:
            projection.weight.normal_(0.0, 0.05)
    with_prior.eval()
    first = with_prior(image, sparse)
    with_prior.prior = KnownPrior(near.flip(-1))  # another prior, same image and radar
    assert (with_prior(image, sparse) - first).abs().max() > 1e-4


def test_the_branch_takes_five_levels_only():
    with pytest.raises(ValueError, match=r"expected five each"):
        PriorBranch((16, 32, 64))
