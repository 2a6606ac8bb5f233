"""Tiny random Depth Anything networks and priors of known shape, for the prior's tests."""

from __future__ import annotations

import os
import socket

import pytest
import torch
import transformers


def refuse_network(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any connection attempt fails the test: the prior reads local files only."""
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.setenv("HTTPS_PROXY", "http://127.0.0.1:9")
    monkeypatch.setenv("HTTP_PROXY", "http://127.0.0.1:9")

    def refuse(*args, **kwargs):
        raise AssertionError("the prior reached for the network")

    monkeypatch.setattr(socket.socket, "connect", refuse)


def offline_environment() -> dict[str, str]:
    """A command's environment with the hub's offline switch unset and proxies pointing
    nowhere: a command that reached for the network would fail."""
    environment = {**os.environ, "HTTPS_PROXY": "http://127.0.0.1:9", "HTTP_PROXY": ""}
    environment.pop("HF_HUB_OFFLINE", None)
    return environment


def tiny_depth_anything(
    width: int = 4,
    depth: int = 2,
    necks=(2, 2),
    out_indices=(1, 2),
    kind: str = "relative",
    max_depth: int | None = None,
):
    """A random Depth Anything of transformers' own test sizes (hidden size 4, 2 layers):
    relative (its head ends in a ReLU), or metric (a sigmoid times ``max_depth`` metres)."""
    torch.manual_seed(0)
    ranges = {} if max_depth is None else {"max_depth": max_depth}
    backbone = transformers.Dinov2Config(
        image_size=28,
        patch_size=14,
        hidden_size=width,
        num_hidden_layers=depth,
        num_attention_heads=max(1, width // 64) if width >= 64 else 2,
        out_indices=list(out_indices),
        apply_layernorm=True,
        reshape_hidden_states=False,
    )
    config = transformers.DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=14,
        reassemble_hidden_size=width,
        reassemble_factors=[4, 2, 1, 0.5][: len(necks)],
        neck_hidden_sizes=list(necks),
        fusion_hidden_size=6,
        head_hidden_size=4,
        depth_estimation_type=kind,
        **ranges,
    )
    model = transformers.DepthAnythingForDepthEstimation(config).eval()
    with torch.no_grad():  # transformers' init leaves a tiny head flat; spread the weights
        for parameter in model.parameters():
            parameter.normal_(0.0, 0.3)
        # a relative head ends in ReLU: keep most pixels above 0; a metric one in a sigmoid:
        # centred, so its metres spread over the range
        model.head.conv3.bias.fill_(0.5 if kind == "relative" else 0.0)
    return model


class KnownPrior(torch.nn.Module):
    """A prior that is an affine map of the true inverse depth (what a perfect relative prior
    gives), standing in for the network after the model is built."""

    def __init__(self, depth: torch.Tensor) -> None:
        super().__init__()
        self.depth = depth

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return 3.0 / self.depth + 0.25
