"""The foundation prior (Depth Anything V2 through transformers, weights from local files) and its
global alignment to sparse metric depth: tiny random networks built and saved by the tests, never
downloaded."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
import torch
import transformers
from helpers.prior import KnownPrior, offline_environment, refuse_network, tiny_depth_anything
from safetensors.torch import load_file
from torch.nn import functional as F

from fusion_depth.errors import ArgumentError, ArgumentFileError
from fusion_depth.models.depth_prior import (
    OUT_INDICES,
    DepthAnythingPrior,
    authors_network_size,
    build_prior,
    load_depth_anything_v2,
    normalized_prior,
    short_side,
)


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    refuse_network(monkeypatch)


@pytest.fixture(scope="module")
def tiny_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_depth_anything")
    tiny_depth_anything().save_pretrained(folder)
    return folder


def test_folder_loads_offline_and_predicts_at_the_input_size(tiny_folder):
    prior = DepthAnythingPrior(tiny_folder, input_size=None)
    assert (prior.kind, prior.max_depth) == ("relative", None)  # from its config.json
    image = torch.rand(2, 3, 64, 96)
    relative = prior(image)
    assert relative.shape == (2, 1, 64, 96)
    assert (relative >= 0).all() and relative.std() > 0
    # the same network straight from transformers, at the size the prior feeds it (70 × 98):
    # resized bicubically (antialiased), normalised, and its output resized back bilinearly
    # with align_corners, as the authors' infer_image does
    network = transformers.DepthAnythingForDepthEstimation.from_pretrained(tiny_folder)
    assert prior.network_size(64, 96) == (70, 98)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    resized = F.interpolate(image, (70, 98), mode="bicubic", antialias=True, align_corners=False)
    with torch.no_grad():
        expected = network(pixel_values=(resized - mean) / std).predicted_depth[:, None]
    expected = F.interpolate(expected, (64, 96), mode="bilinear", align_corners=True)
    torch.testing.assert_close(relative, expected.clamp_min(0))


def test_prior_is_frozen(tiny_folder):
    prior = DepthAnythingPrior(tiny_folder, input_size=28).train()
    assert not prior.network.training
    assert not any(p.requires_grad for p in prior.parameters())
    image = torch.rand(1, 3, 32, 48, requires_grad=True)
    assert not prior(image).requires_grad
    assert prior.network_size(32, 48) == (28, 42)  # short side 28, long side to the nearest 14


# The authors' names, written from transformers' on-disk ones: the inverse of the loader's map,
# spelt out separately. It shows the loader applies its map consistently; whether the map is the
# authors' can only be checked against their code, which is not in this repository (it was,
# outside it, when the map was written: outputs within 1.5e-5 at 518 × 518).
def official_names(hf: dict) -> dict:
    out = {}
    for name, tensor in hf.items():
        m = re.match(r"backbone\.encoder\.layer\.(\d+)\.attention\.attention\.query\.(\w+)", name)
        if m:
            block, kind = m.groups()
            parts = [
                hf[f"backbone.encoder.layer.{block}.attention.attention.{p}.{kind}"]
                for p in ("query", "key", "value")
            ]
            out[f"pretrained.blocks.{block}.attn.qkv.{kind}"] = torch.cat(parts)
            continue
        if re.search(r"attention\.attention\.(key|value)\.", name):
            continue
        rules = [
            (r"backbone\.embeddings\.cls_token", "pretrained.cls_token"),
            (r"backbone\.embeddings\.mask_token", "pretrained.mask_token"),
            (r"backbone\.embeddings\.position_embeddings", "pretrained.pos_embed"),
            (
                r"backbone\.embeddings\.patch_embeddings\.projection\.",
                "pretrained.patch_embed.proj.",
            ),
            (
                r"backbone\.encoder\.layer\.(\d+)\.layer_scale(\d)\.lambda1",
                r"pretrained.blocks.\1.ls\2.gamma",
            ),
            (
                r"backbone\.encoder\.layer\.(\d+)\.attention\.output\.dense\.",
                r"pretrained.blocks.\1.attn.proj.",
            ),
            (r"backbone\.encoder\.layer\.(\d+)\.", r"pretrained.blocks.\1."),
            (r"backbone\.layernorm\.", "pretrained.norm."),
            (r"neck\.reassemble_stage\.layers\.(\d)\.projection\.", r"depth_head.projects.\1."),
            (r"neck\.reassemble_stage\.layers\.(\d)\.resize\.", r"depth_head.resize_layers.\1."),
            (r"neck\.convs\.(\d)\.weight", None),
            (r"neck\.fusion_stage\.layers\.(\d)\.(.*)", None),
            (r"head\.conv1\.", "depth_head.scratch.output_conv1."),
            (r"head\.conv2\.", "depth_head.scratch.output_conv2.0."),
            (r"head\.conv3\.", "depth_head.scratch.output_conv2.2."),
        ]
        for pattern, replacement in rules:
            m = re.match(pattern, name)
            if not m:
                continue
            if pattern.startswith(r"neck\.convs"):
                new = f"depth_head.scratch.layer{int(m.group(1)) + 1}_rn.weight"
            elif pattern.startswith(r"neck\.fusion"):
                rest = m.group(2).replace("projection.", "out_conv.")
                rest = re.sub(r"residual_layer(\d)\.convolution(\d)", r"resConfUnit\1.conv\2", rest)
                new = f"depth_head.scratch.refinenet{4 - int(m.group(1))}.{rest}"
            else:
                new = re.sub(pattern, replacement, name)
            out[new] = tensor
            break
        else:
            raise AssertionError(f"no rule for {name}")
    return out


@pytest.fixture(scope="module")
def official_checkpoint(tmp_path_factory):
    """A small network in the authors' .pth layout: 64 wide, 12 blocks (ViT-S's depth)."""
    folder = tmp_path_factory.mktemp("official")
    model = tiny_depth_anything(64, 12, (8, 8, 8, 8), OUT_INDICES[12])
    model.save_pretrained(folder / "hf")
    state = official_names(load_file(folder / "hf" / "model.safetensors"))
    torch.save(state, folder / "depth_anything_v2_tiny.pth")
    return folder / "depth_anything_v2_tiny.pth", folder / "hf", state


def test_authors_pth_loads_to_the_same_network(official_checkpoint):
    path, hf_folder, _ = official_checkpoint
    from_pth = load_depth_anything_v2(path)
    from_folder = load_depth_anything_v2(hf_folder)
    pixels = torch.rand(1, 3, 56, 84)
    with torch.no_grad():
        torch.testing.assert_close(
            from_pth(pixel_values=pixels).predicted_depth,
            from_folder(pixel_values=pixels).predicted_depth,
            rtol=0,
            atol=0,
        )


def test_bad_weights_are_one_line_naming_weights(tmp_path, official_checkpoint, tiny_folder):
    _, _, state = official_checkpoint
    with pytest.raises(ArgumentFileError, match=r"^weights=.*missing.*: no such file"):
        DepthAnythingPrior(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ArgumentError, match=r"^weights=.*empty: a folder without config.json"):
        load_depth_anything_v2(tmp_path / "empty")
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.json").write_text(json.dumps({"model_type": "bert"}))
    with pytest.raises(ArgumentError, match=r"a bert model \(expected depth_anything\)"):
        load_depth_anything_v2(other)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "config.json").write_text((tiny_folder / "config.json").read_text())
    (broken / "model.safetensors").write_bytes(b"not safetensors")
    with pytest.raises(ArgumentError, match=r"^weights=.*broken: cannot be loaded"):
        load_depth_anything_v2(broken)
    text = tmp_path / "notes.pth"
    text.write_text("hello")
    with pytest.raises(ArgumentError, match=r"not a readable PyTorch checkpoint"):
        load_depth_anything_v2(text)
    extra = tmp_path / "extra.pth"
    torch.save({**state, "decoder.bias": torch.zeros(1)}, extra)
    with pytest.raises(ArgumentError, match=r"unexpected keys decoder.bias"):
        load_depth_anything_v2(extra)
    narrow = tmp_path / "narrow.pth"  # another size: a width no Depth Anything V2 has
    torch.save({**state, "pretrained.cls_token": state["pretrained.cls_token"][..., :48]}, narrow)
    with pytest.raises(ArgumentError, match=r"48 wide and 12 blocks deep"):
        load_depth_anything_v2(narrow)
    cut = tmp_path / "cut.pth"  # a tensor of the wrong shape for its config
    torch.save({**state, "depth_head.scratch.output_conv1.bias": torch.zeros(5)}, cut)
    with pytest.raises(ArgumentError, match=r"^weights=.*cut.pth: does not fit Depth Anything V2"):
        load_depth_anything_v2(cut)
    with pytest.raises(ArgumentError, match=r"^input_size=7: expected an integer ≥ 14"):
        DepthAnythingPrior(tiny_folder, input_size=7)


# --- preprocessing: the authors' sizes, transformers' resize ---------------------------------


def authors_get_size(height, width, target, multiple=14):
    """The authors' ``Resize.get_size`` (``depth_anything_v2/util/transform.py``) for
    ``keep_aspect_ratio=True, resize_method="lower_bound"``, spelt out in numpy as they wrote it."""

    def constrain(x, min_val):
        y = (np.round(x / multiple) * multiple).astype(int)
        if y < min_val:
            y = (np.ceil(x / multiple) * multiple).astype(int)
        return int(y)

    scale_height, scale_width = target / height, target / width
    if scale_width > scale_height:
        scale_height = scale_width
    else:
        scale_width = scale_height
    return constrain(scale_height * height, target), constrain(scale_width * width, target)


def test_network_size_is_the_authors_lower_bound():
    sizes = [(h, w) for h in range(5, 240, 9) for w in range(5, 700, 23)]
    sizes += [(64, 192), (900, 1600), (375, 1242), (97, 131), (518, 518), (259, 1777)]
    for target in (14, 28, 100, 500, 510, 518):
        for height, width in sizes:
            ours = authors_network_size(height, width, target)
            assert ours == authors_get_size(height, width, target), (height, width, target)
            assert min(ours) >= target and ours[0] % 14 == ours[1] % 14 == 0
    # Rounded half to even, and up where the nearest multiple falls below the target: 21 is
    # 1.5 patches (to 28), 35 is 2.5 (to 28, then up to 42 as below the target 35).
    assert authors_network_size(21, 21, 21) == (28, 28)
    assert authors_network_size(35, 35, 35) == (42, 42)
    # transformers' processor (keep_aspect_ratio: "scale as little as possible") agrees where the
    # image is scaled down, and puts a small image's long side at 518 where the authors put its
    # short side: 64 × 192 is 168 × 518 there, 518 × 1554 here.
    from transformers.models.dpt.image_processing_dpt import get_resize_output_image_size

    def processor_size(height, width):
        image = np.zeros((3, height, width), dtype=np.uint8)
        got = get_resize_output_image_size(image, (518, 518), True, 14)
        return (got.height, got.width) if hasattr(got, "height") else tuple(got)  # 5 | 4.x

    for height, width in [(900, 1600), (375, 1242), (600, 800), (1080, 1920)]:
        assert processor_size(height, width) == authors_network_size(height, width, 518)
    assert processor_size(64, 192) == (168, 518)
    assert authors_network_size(64, 192, 518) == (518, 1554)


def test_the_short_side_each_input_size_gives():
    assert short_side(64, 192, 518) == 518
    assert short_side(64, 192, None) == 64
    assert short_side(64, 192, "auto") == 64  # a small frame at its own resolution
    assert short_side(900, 1600, "auto") == 518  # a large one as the authors see it
    assert short_side(1600, 900, None) == 900


def _processor():
    """transformers' processor as the Hub's Depth-Anything-V2-*-hf preprocessor_config.json sets
    it (built here: nothing downloaded)."""
    return transformers.DPTImageProcessor(
        do_resize=True,
        size={"height": 518, "width": 518},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        resample=3,  # PIL's BICUBIC
        do_rescale=True,
        rescale_factor=1 / 255,
        do_normalize=True,
        image_mean=[0.485, 0.456, 0.406],
        image_std=[0.229, 0.224, 0.225],
        do_pad=False,
    )


@pytest.mark.parametrize("input_size", [518, "auto", None])
def test_preprocessing_matches_transformers_processor(tiny_folder, input_size):
    processor = _processor()
    prior = DepthAnythingPrior(tiny_folder, input_size=input_size)
    generator = torch.Generator().manual_seed(0)
    for height, width in [(64, 192), (97, 131), (33, 47), (375, 1242), (900, 1600)]:
        image = torch.rand(2, 3, height, width, generator=generator)
        ours = prior.preprocess(image)
        size = prior.network_size(height, width)
        assert ours.shape == (2, 3, *size)
        theirs = processor(
            images=list(image * 255),
            size={"height": size[0], "width": size[1]},  # the authors' size, given
            keep_aspect_ratio=False,
            return_tensors="pt",
        )["pixel_values"]
        torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-4)
        if input_size == 518 and min(height, width) > 518:  # scaled down: its own size too
            own = processor(images=list(image * 255), return_tensors="pt")["pixel_values"]
            torch.testing.assert_close(ours, own, rtol=0, atol=1e-4)


# --- relative and metric Depth Anything ------------------------------------------------------


@pytest.fixture(scope="module")
def metric_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_metric")
    tiny_depth_anything(kind="metric", max_depth=80).save_pretrained(folder)
    return folder


@pytest.fixture(scope="module")
def metric_pth(official_checkpoint, tmp_path_factory):
    """The authors' layout under a metric name: the same tensors as a relative .pth (their
    metric head's sigmoid has no weights), as their metric checkpoints are."""
    _, _, state = official_checkpoint
    folder = tmp_path_factory.mktemp("metric_pth")
    torch.save(state, folder / "depth_anything_v2_metric_vkitti_vits.pth")
    torch.save(state, folder / "depth_anything_v2_vits.pth")  # the authors' relative name
    torch.save(state, folder / "finetuned.pth")  # a name that says neither
    return folder


def test_a_metric_folder_outputs_metres(metric_folder, tmp_path):
    prior = DepthAnythingPrior(metric_folder, input_size=28)
    assert (prior.kind, prior.max_depth) == ("metric", 80.0)  # from its config.json
    image = torch.rand(2, 3, 32, 48)
    metres = prior(image)
    assert metres.shape == (2, 1, 32, 48)
    assert (metres > 0).all() and (metres <= 80).all() and metres.std() > 1
    # transformers' own metric head (sigmoid × 80), at the size the prior feeds it
    network = transformers.DepthAnythingForDepthEstimation.from_pretrained(metric_folder)
    with torch.no_grad():
        expected = network(pixel_values=prior.preprocess(image)).predicted_depth[:, None]
    expected = F.interpolate(expected, (32, 48), mode="bilinear", align_corners=True)
    torch.testing.assert_close(metres, expected)
    # Given, the folder's own settings are accepted; a range the folder has none of is used.
    assert DepthAnythingPrior(metric_folder, 28, kind="metric", max_depth=80).kind == "metric"
    config = json.loads((metric_folder / "config.json").read_text())
    del config["max_depth"]
    unranged = tmp_path / "unranged"
    shutil.copytree(metric_folder, unranged)
    (unranged / "config.json").write_text(json.dumps(config))
    fifty = DepthAnythingPrior(unranged, 28, max_depth=50)
    torch.testing.assert_close(fifty(image), metres * 50 / 80)


def test_a_metric_pth_loads_as_metric_with_its_range(metric_pth, official_checkpoint):
    path = metric_pth / "depth_anything_v2_metric_vkitti_vits.pth"
    prior = build_prior("depth_anything_v2", str(path), 28, kind="metric", max_depth=80)
    assert (prior.kind, prior.max_depth) == ("metric", 80.0)
    metres = prior(torch.rand(1, 3, 32, 48))
    assert (metres > 0).all() and (metres <= 80).all()
    # The same tensors read as relative (the authors' relative name): ReLU(z) there, and
    # 80 · sigmoid(z) here, the metric head of metric_depth/depth_anything_v2/dpt.py.
    relative = load_depth_anything_v2(metric_pth / "depth_anything_v2_vits.pth")
    metric = load_depth_anything_v2(path, "metric", 80)
    pixels = torch.randn(1, 3, 56, 84)
    with torch.no_grad():
        z = relative(pixel_values=pixels).predicted_depth
        depth = metric(pixel_values=pixels).predicted_depth
    assert (z > 0).float().mean() > 0.2
    torch.testing.assert_close(depth[z > 0], 80 * torch.sigmoid(z[z > 0]))
    assert metric.config.depth_estimation_type == "metric" and metric.config.max_depth == 80
    # A name that says neither is what kind says: 12.5 m, a range no integer config can hold.
    odd = load_depth_anything_v2(metric_pth / "finetuned.pth", "metric", 12.5)
    with torch.no_grad():
        assert odd(pixel_values=pixels).predicted_depth.max() <= 12.5


def one_line(raised, pattern):
    message = str(raised.value)
    assert re.match(pattern, message), message
    assert "\n" not in message and len(message) < 500, message
    return message


def test_a_metric_pth_cannot_be_read_as_relative(metric_pth):
    path = metric_pth / "depth_anything_v2_metric_vkitti_vits.pth"
    for kind in (None, "relative"):
        with pytest.raises(ArgumentError) as raised:
            DepthAnythingPrior(path, kind=kind)
        message = one_line(raised, rf"^kind={kind or 'null'}: {re.escape(str(path))} is named as")
        assert "expected kind=metric max_depth=80" in message
    with pytest.raises(ArgumentError) as raised:  # no range: the file holds none
        DepthAnythingPrior(path, kind="metric")
    one_line(raised, r"^max_depth=null: .*records no range: expected max_depth=80 \(vkitti")
    with pytest.raises(ArgumentError) as raised:  # the authors' outdoor model, given indoor's
        DepthAnythingPrior(path, kind="metric", max_depth=20)
    one_line(raised, r"^max_depth=20: .*expected max_depth=80")
    hypersim = metric_pth / "depth_anything_v2_metric_hypersim_vits.pth"
    shutil.copy(path, hypersim)
    with pytest.raises(ArgumentError) as raised:
        DepthAnythingPrior(hypersim, kind="metric", max_depth=80)
    one_line(raised, r"^max_depth=80: .*expected max_depth=20 \(hypersim")
    with pytest.raises(ArgumentError) as raised:  # the reverse: a relative name read as metric
        DepthAnythingPrior(metric_pth / "depth_anything_v2_vits.pth", kind="metric", max_depth=80)
    one_line(raised, r"^kind=metric: .*depth_anything_v2_vits.pth is named as the authors' rel")
    with pytest.raises(ArgumentError) as raised:  # a relative prior has no range
        DepthAnythingPrior(metric_pth / "finetuned.pth", max_depth=80)
    one_line(raised, r"^max_depth=80: a relative prior \(kind=relative\) .*expected null")
    # The commands name the config keys.
    from fusion_depth.config.arguments import config_message

    with pytest.raises(ArgumentError) as raised:
        DepthAnythingPrior(path)
    message = config_message(raised.value)
    assert message.startswith("prior.kind=null: ")
    assert "expected prior.kind=metric prior.max_depth=80" in message


def test_a_folder_of_one_kind_refuses_the_other(metric_folder, tiny_folder):
    with pytest.raises(ArgumentError) as raised:
        DepthAnythingPrior(metric_folder, kind="relative")
    file = re.escape(str(metric_folder / "config.json"))
    one_line(raised, rf'^kind=relative: {file} sets depth_estimation_type="metric"')
    with pytest.raises(ArgumentError) as raised:
        DepthAnythingPrior(tiny_folder, kind="metric", max_depth=80)
    file = re.escape(str(tiny_folder / "config.json"))
    one_line(raised, rf'^kind=metric: {file} sets depth_estimation_type="relative"')
    with pytest.raises(ArgumentError) as raised:
        DepthAnythingPrior(metric_folder, max_depth=20)
    one_line(raised, r"^max_depth=20: .*config.json sets max_depth=80, .*expected null .* or 80")
    with pytest.raises(ArgumentError) as raised:
        DepthAnythingPrior(tiny_folder, max_depth=80)
    one_line(raised, r"^max_depth=80: a relative prior")
    for kind, max_depth, pattern in [
        ("metres", None, r"^kind='metres': expected one of \[None, 'relative', 'metric'\]"),
        (None, -1, r"^max_depth=-1: expected a number of metres > 0, or null"),
        (None, float("inf"), r"^max_depth=inf: expected a number of metres > 0"),
    ]:
        with pytest.raises(ArgumentError) as raised:
            DepthAnythingPrior(tiny_folder, kind=kind, max_depth=max_depth)
        one_line(raised, pattern)
    with pytest.raises(ArgumentError) as raised:
        DepthAnythingPrior(tiny_folder, input_size="big")
    one_line(raised, r"^input_size='big': expected an integer ≥ 14, null .* or auto")


def test_the_prior_settings_rules():
    from fusion_depth.models.depth_prior import ARGUMENT_RULES

    rules = ARGUMENT_RULES
    assert all(rules["input_size"].ok(v) for v in (14, 518, None, "auto"))
    assert not any(rules["input_size"].ok(v) for v in (13, "big", 20.0, True))
    assert all(rules["kind"].ok(v) for v in (None, "relative", "metric"))
    assert not rules["kind"].ok("metres")
    assert all(rules["max_depth"].ok(v) for v in (None, 20, 80.0))
    assert not any(rules["max_depth"].ok(v) for v in (0, -5, True, "80", float("nan")))


def test_a_checkpoint_records_and_checks_the_kind_of_its_prior(metric_pth, tiny_folder):
    from fusion_depth.models.depth_prior import check_prior_record, prior_record
    from fusion_depth.utils.checkpoint_file import CheckpointError

    path = metric_pth / "finetuned.pth"  # a name that says neither: read either way
    net = torch.nn.Module()
    net.prior = DepthAnythingPrior(path, input_size=28, kind="metric", max_depth=80)
    record = prior_record(net)
    assert (record["kind"], record["max_depth"]) == ("metric", 80.0)
    check_prior_record(net, record, "ckpt_path=x.ckpt")  # the same reading
    trained = {**record, "kind": "relative", "max_depth": None}  # trained on the relative one
    with pytest.raises(CheckpointError) as raised:
        check_prior_record(net, trained, "ckpt_path=x.ckpt")
    message = one_line(raised, r"^ckpt_path=x.ckpt: its network was trained with .* read as ")
    assert "kind=relative, but it is now read as kind=metric max_depth=80" in message
    assert message.endswith("give prior.kind=relative")
    # A record from before the kind was recorded held a relative prior.
    net.prior = DepthAnythingPrior(tiny_folder, input_size=28)
    old = {k: v for k, v in prior_record(net).items() if k not in ("kind", "max_depth")}
    check_prior_record(net, old, "ckpt_path=x.ckpt")


# The global alignment's tests: tests/test_alignment.py.


# --- the prior as a further input of DenseDepth ------------------------------------------------


def prior_net(folder, dropout=0.0, seed=0):
    from fusion_depth.models import DepthNet

    torch.manual_seed(seed)
    spec = {"name": "depth_anything_v2", "weights": str(folder), "input_size": 28}
    return DepthNet(backbone="resnet10t", fusion="concat", prior={**spec, "dropout": dropout})


def test_densedepth_takes_the_prior_and_checkpoints_leave_it_out(tiny_folder):
    from fusion_depth.models import DepthNet

    net = prior_net(tiny_folder).eval()
    image, sparse = torch.rand(2, 3, 64, 96), torch.rand(2, 1, 64, 96) * 40
    out = net(image, sparse)
    assert out.shape == (2, 1, 32, 48)
    state = net.state_dict()
    assert not any(k.startswith("prior.") for k in state)  # the prior's weights stay in its files
    assert any(k.startswith("prior_branch.") for k in state)  # its own input branch
    again = prior_net(tiny_folder, seed=1).eval()  # other random weights, the same prior
    again.load_state_dict(state)  # strict: the prior fills its own weights in
    torch.testing.assert_close(again(image, sparse), out)
    # No prior: a network built without the argument has the keys checkpoints before it had.
    plain = DepthNet(backbone="resnet10t", fusion="concat")
    assert plain.prior is None and plain.prior_branch is None
    with_none = DepthNet(backbone="resnet10t", fusion="concat", prior={"name": "none"})
    assert set(with_none.state_dict()) == set(plain.state_dict())


def test_prior_dropout_gives_some_frames_none_in_training_only(tiny_folder):
    image = torch.rand(64, 3, 32, 32)
    net = prior_net(tiny_folder, dropout=0.5)
    with torch.no_grad():
        full = net.eval().prior_input(image)
        assert (full.amax(dim=(1, 2, 3)) == 1).all()  # normalised per frame: max 1, min 0
        dropped = net.train().prior_input(image)
    zero = dropped.amax(dim=(1, 2, 3)) == 0
    assert 10 < int(zero.sum()) < 54  # about half of 64 frames
    torch.testing.assert_close(dropped[~zero], full[~zero])


def _train(tmp_path, *overrides, env=None):
    from helpers import run_module

    return run_module(
        ["fusion_depth.train", "experiment=smoke", "logger=none", *overrides],
        cwd=tmp_path,
        env=offline_environment() if env is None else env,
    )


def evaluates_and_exports(run, cwd):
    """The run's checkpoint, whose prior is built again from its file, scores with ``evaluate``
    and exports to ONNX, verified by onnxruntime."""
    from helpers import run_module

    (checkpoint,) = (run / "checkpoints").glob("epoch*.ckpt")
    evaluated = run_module(
        ["fusion_depth.evaluate", f"ckpt_path={checkpoint}", f"hydra.run.dir={run}/evaluate"],
        cwd=cwd,
    )
    assert evaluated.returncode == 0, evaluated.stderr[-2000:]
    rescored = json.loads((run / "evaluate" / "metrics.json").read_text())
    tested = json.loads((run / "metrics.json").read_text())
    assert rescored["test"]["rmse"] == pytest.approx(tested["test"]["rmse"], rel=1e-4)
    exported = run_module(
        ["fusion_depth.export", f"ckpt_path={checkpoint}", "format=onnx", f"hydra.run.dir={run}/x"],
        cwd=cwd,
    )
    assert exported.returncode == 0, exported.stderr[-2000:]
    assert "verified with onnxruntime" in exported.stderr + exported.stdout


@pytest.mark.slow
def test_smoke_run_trains_with_the_prior_evaluates_and_exports(tmp_path, tiny_folder):
    run = tmp_path / "run"
    done = _train(
        tmp_path, "prior=depth_anything_v2", f"prior.weights={tiny_folder}", f"hydra.run.dir={run}"
    )
    assert done.returncode == 0, done.stderr[-2000:]
    record = json.loads((run / "metrics.json").read_text())
    assert record["test"]["rmse"] > 0
    resolved = (run / "config_resolved.yaml").read_text()
    assert "depth_anything_v2" in resolved
    evaluates_and_exports(run, tmp_path)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["prior.weights=/no/such/prior"], "prior.weights=/no/such/prior: no such file or folder"),
        (["prior.weights={tiny}", "prior.input_size=7"], "prior.input_size=7: expected an integer"),
        (["prior.weights={tiny}", "prior.dropout=2"], "prior.dropout=2: expected a probability"),
        (["prior.weights={tiny}", "prior.kind=metres"], "prior.kind=metres: expected one of null"),
        (
            ["prior.weights={tiny}", "prior.input_size=auto", "prior.kind=metric"],
            "prior.kind=metric: ",
        ),
        (
            ["prior.weights={tiny}", "model=radarnet", "fusion=concat"],
            "model=radarnet cannot take prior=depth_anything_v2: it takes no prior",
        ),
    ],
)
@pytest.mark.slow
def test_bad_prior_settings_fail_in_one_line(tmp_path, tiny_folder, overrides, message):
    overrides = [o.replace("{tiny}", str(tiny_folder)) for o in overrides]
    failed = _train(tmp_path, "prior=depth_anything_v2", *overrides, f"hydra.run.dir={tmp_path}/r")
    assert failed.returncode == 1
    assert message in failed.stderr
    assert "Traceback" not in failed.stderr
    assert not (tmp_path / "r" / "checkpoints").exists()


# --- model=prior_correction: the aligned prior times a learned scale map ------------------------


def test_correction_with_a_zero_learner_output_is_the_global_alignment(tiny_folder):
    """``d · ReLU(1 + out)``: where the learner outputs 0, the aligned prior itself; a frame
    without returns takes the running fit, which training moves towards the batch's fits."""
    from fusion_depth.models import create_model

    torch.manual_seed(0)
    depth = 2.0 + 40.0 * torch.rand(2, 1, 64, 96)
    sparse = torch.zeros_like(depth)
    picked = torch.rand_like(depth) < 0.05
    sparse[picked] = depth[picked]
    prior = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    net = create_model("prior_correction", prior=prior, fusion="concat")
    net.prior = KnownPrior(depth)
    last = net.learner.scratch.output_conv.output_conv[4]  # the last 1×1 conv
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    out = net.eval()(torch.rand(2, 3, 64, 96), sparse)
    assert out.shape == depth.shape  # at the input's resolution, as their learner
    torch.testing.assert_close(net.depth_scale / out, depth, rtol=1e-4, atol=0)
    assert net.fit_summary()["fits"] == 2 and net.fit_summary()["fallbacks"] == 0
    assert net.fit_mean.tolist() == [1.0, 0.0]
    normalised = normalized_prior(KnownPrior(depth)(None))
    net.train().aligned_inverse(KnownPrior(depth)(None), sparse, None)
    fitted = net.fit_mean.clone()
    assert fitted[0].item() != 1.0  # moved towards the batch's median fit
    none = net.eval().aligned_inverse(KnownPrior(depth)(None), torch.zeros_like(sparse), None)
    torch.testing.assert_close(none, (fitted[0] * normalised + fitted[1]).clamp(1 / 80.0, 1 / 0.5))
    assert not any(k.startswith("prior.") for k in net.state_dict())


@pytest.mark.slow
def test_correction_trains_evaluates_and_exports(tmp_path, tiny_folder):
    run = tmp_path / "run"
    overrides = ["model=prior_correction", "fusion=concat", "prior=depth_anything_v2"]
    done = _train(tmp_path, *overrides, f"prior.weights={tiny_folder}", f"hydra.run.dir={run}")
    assert done.returncode == 0, done.stderr[-2000:]
    record = json.loads((run / "metrics.json").read_text())
    assert record["test"]["rmse"] > 0
    # The test stage's fits, one per frame, counted in the record (a random prior's fit may
    # reverse the depths, which falls back too).
    assert record["alignment"]["fits"] == record["test"]["num_images"]
    assert 0 <= record["alignment"]["fallbacks"] <= record["alignment"]["fits"]
    evaluates_and_exports(run, tmp_path)
    refused = _train(tmp_path, "model=prior_correction", "fusion=concat", f"hydra.run.dir={run}2")
    assert refused.returncode == 1
    assert "prior=none: model=prior_correction works on a monocular prior" in refused.stderr
    assert "Traceback" not in refused.stderr


# --- prior=checkpoint: a network of this platform as the prior ---------------------------------

DATASET = {"name": "procedural", "min_depth": 0.5, "max_depth": 80.0, "depth_scale": 10.0}


def test_a_platform_checkpoint_serves_as_the_prior(tmp_path):
    from helpers import save_untrained_checkpoint

    from fusion_depth.models import DepthNet
    from fusion_depth.models.depth_prior import CheckpointPrior

    path = save_untrained_checkpoint(
        tmp_path / "rgb.ckpt", "rgb", DATASET, backbone="resnet10t", spread=True
    )
    prior = CheckpointPrior(path)
    assert (prior.kind, prior.max_depth) == ("relative", None)
    with pytest.raises(ArgumentError, match=r"^kind=metric: prior=checkpoint is relative"):
        build_prior("checkpoint", str(path), None, kind="metric")
    with pytest.raises(ArgumentError, match=r"^max_depth=80: a relative prior"):
        CheckpointPrior(path, max_depth=80)
    image = torch.rand(2, 3, 64, 96)
    relative = prior.train()(image)
    assert relative.shape == (2, 1, 64, 96) and not prior.network.training
    # its raw output (reciprocal depth), resized to the image
    with torch.no_grad():
        raw = prior.network(image, None)
    expected = torch.nn.functional.interpolate(raw, (64, 96), mode="bilinear")
    torch.testing.assert_close(relative, expected)
    assert CheckpointPrior(path, input_size=32)(image).shape == (2, 1, 64, 96)  # sees 32 × 64
    assert CheckpointPrior(path, input_size="auto")(image).shape == (2, 1, 64, 96)  # 64 × 96
    net = DepthNet(backbone="resnet10t", prior={"name": "checkpoint", "weights": str(path)})
    assert net(image).shape == (2, 1, 32, 48)
    assert not any(k.startswith("prior.") for k in net.state_dict())

    concat = save_untrained_checkpoint(
        tmp_path / "concat.ckpt", "concat", DATASET, backbone="resnet10t"
    )
    with pytest.raises(
        ArgumentError, match=r"^weights=.*concat.ckpt: a network with fusion=concat"
    ):
        CheckpointPrior(concat)
    with pytest.raises(ArgumentFileError, match=r"^weights=.*nothing.ckpt: no such file"):
        CheckpointPrior(tmp_path / "nothing.ckpt")
    (tmp_path / "notes.ckpt").write_text("not a checkpoint")
    with pytest.raises(ArgumentError, match=r"^weights=.*notes.ckpt: "):
        CheckpointPrior(tmp_path / "notes.ckpt")


@pytest.mark.slow
def test_smoke_run_with_a_checkpoint_prior(tmp_path):
    from helpers import save_untrained_checkpoint

    path = save_untrained_checkpoint(tmp_path / "rgb.ckpt", "rgb", DATASET, backbone="resnet10t")
    run = tmp_path / "run"
    done = _train(tmp_path, "prior=checkpoint", f"prior.weights={path}", f"hydra.run.dir={run}")
    assert done.returncode == 0, done.stderr[-2000:]
    assert (run / "metrics.json").is_file()
    missing = _train(tmp_path, "prior=checkpoint", f"hydra.run.dir={run}2")
    assert missing.returncode == 1
    assert "prior.weights: missing value (???)" in missing.stderr


def test_what_a_prior_must_be(tmp_path, tiny_folder):
    """Refused in one line: a checkpoint that predicts metres. (A fit that would reverse the
    order of depths: tests/test_alignment.py; a metric Depth Anything is a prior of kind metric,
    above.)"""
    from fusion_depth.models import create_model
    from fusion_depth.models.depth_prior import CheckpointPrior

    torch.manual_seed(0)
    net = create_model("sparse_to_dense", backbone="resnet18", fusion="rgb")
    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    config = {
        "model": {"net": {"name": "sparse_to_dense", "backbone": "resnet18", "fusion": "rgb"}}
    }
    torch.save({"state_dict": state, "fusion_depth_config": config}, tmp_path / "metres.ckpt")
    with pytest.raises(ArgumentError, match=r"model=sparse_to_dense predicts metres"):
        CheckpointPrior(tmp_path / "metres.ckpt")


def test_the_fit_runs_in_fp32_under_bf16_autocast(tiny_folder):
    torch.manual_seed(0)
    depth = 2.0 + 40.0 * torch.rand(1, 1, 64, 96)
    sparse = torch.where(torch.rand_like(depth) < 0.03, depth, 0.0)
    prior = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    from fusion_depth.models import create_model

    net = create_model("prior_correction", prior=prior, fusion="concat")
    relative = (3.0 / depth + 0.01).bfloat16()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        inverse = net.eval().aligned_inverse(relative, sparse, None)
    assert inverse.dtype == torch.float32
    exact = net.aligned_inverse(relative.float(), sparse, None)
    torch.testing.assert_close(inverse, exact)


# --- bad prior files, weights folders that would reach the network, priors replaced ------------


def _bad_checkpoints(folder, good):
    """Files ``prior=checkpoint`` may be given that are not a checkpoint ``train`` wrote, by
    what is wrong with them: ``(path, what the message says is expected)``."""
    checkpoint = torch.load(good, weights_only=True)
    state = checkpoint["state_dict"]
    variants = {
        "list_state": ({**checkpoint, "state_dict": list(state.values())}, "mapping of parameter"),
        "text_state": ({**checkpoint, "state_dict": "weights"}, "mapping of parameter"),
        "int_values": ({**checkpoint, "state_dict": dict.fromkeys(state, 1)}, "mapping of param"),
        "int_keys": ({**checkpoint, "state_dict": dict(enumerate(state.values()))}, "mapping of"),
        "no_state": ({k: v for k, v in checkpoint.items() if k != "state_dict"}, "state_dict"),
        "no_net": ({**checkpoint, "fusion_depth_config": {"model": [1]}}, "names no network"),
        "not_a_mapping": ([1, 2, 3], "state_dict"),
    }
    cases = []
    for name, (content, expected) in variants.items():
        torch.save(content, folder / f"{name}.ckpt")
        cases.append((folder / f"{name}.ckpt", expected))
    raw = good.read_bytes()
    (folder / "truncated.ckpt").write_bytes(raw[: len(raw) // 2])
    (folder / "text.ckpt").write_text("hello, not a checkpoint")
    (folder / "empty.ckpt").write_bytes(b"")
    readable = "not a readable PyTorch checkpoint"
    cases += [(folder / f"{n}.ckpt", readable) for n in ("truncated", "text", "empty")]
    return cases


def test_a_bad_prior_checkpoint_is_one_line_naming_it(tmp_path):
    from helpers import save_untrained_checkpoint

    from fusion_depth.models.depth_prior import CheckpointPrior

    good = save_untrained_checkpoint(tmp_path / "rgb.ckpt", "rgb", DATASET, backbone="resnet10t")
    before = {p: p.read_bytes() for p in tmp_path.iterdir()}
    for path, expected in _bad_checkpoints(tmp_path, good):
        with pytest.raises(ArgumentError) as raised:
            CheckpointPrior(path)
        message = str(raised.value)
        assert message.startswith(f"weights={path}: "), message
        assert expected in message and "\n" not in message and len(message) < 400, message
    assert all(p.read_bytes() == data for p, data in before.items())  # nothing written over


HUB_CONFIGS = [
    ({"backbone": "facebook/dinov2-small", "backbone_config": None}, "backbone"),
    ({"use_pretrained_backbone": True}, "use_pretrained_backbone"),
    ({"backbone": "vit_small_patch14_dinov2", "use_timm_backbone": True}, "backbone"),
    ({"use_timm_backbone": True}, "use_timm_backbone"),
    ({"backbone_config": "facebook/dinov2-small"}, "backbone_config"),
]


def _hub_folder(tmp_path, tiny_folder, edit):
    folder = tmp_path / "weights"
    shutil.copytree(tiny_folder, folder)
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**config, **edit}))
    return folder


def _count_network(monkeypatch):
    """Every connection or name lookup attempted, refused (recorded: a loader that catches
    the error cannot hide that it tried)."""
    import socket

    attempts = []

    def refuse(*args, **kwargs):
        attempts.append(args)
        raise OSError("the network is not reachable in this test")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    return attempts


@pytest.mark.parametrize(("edit", "key"), HUB_CONFIGS)
def test_a_config_naming_a_hub_backbone_never_reaches_the_network(
    tmp_path, tiny_folder, monkeypatch, edit, key
):
    import os

    attempts = _count_network(monkeypatch)
    folder = _hub_folder(tmp_path, tiny_folder, edit)
    with pytest.raises(ArgumentError) as raised:
        DepthAnythingPrior(folder)
    message = str(raised.value)
    assert message.startswith(f"weights={folder}: {folder / 'config.json'} sets {key}=")
    assert "local files only" in message and "\n" not in message
    assert attempts == []
    assert "HF_HUB_OFFLINE" not in os.environ  # the offline switch is put back as it was


@pytest.mark.parametrize(("edit", "key"), HUB_CONFIGS)
def test_the_folder_is_read_with_every_download_path_off(
    tmp_path, tiny_folder, monkeypatch, edit, key
):
    """Past the check of config.json (skipped here), the hub's offline switch still stops
    any request: the folder loads from its own files or is refused in one line, and no
    connection is attempted."""
    from fusion_depth.models import depth_prior

    attempts = _count_network(monkeypatch)
    monkeypatch.setattr(depth_prior, "_check_local_config", lambda *args: None, raising=False)
    folder = _hub_folder(tmp_path, tiny_folder, edit)
    try:
        load_depth_anything_v2(folder)
    except ArgumentError as err:
        assert str(err).startswith(f"weights={folder}: ") and "\n" not in str(err)
    else:  # the backbone is described in the folder: nothing to fetch
        assert isinstance(edit.get("backbone_config", {}), dict)
    assert attempts == []


def _checkpoint_with_prior(path, folder):
    """A network with ``folder`` as its prior, saved as training saves it."""
    from fusion_depth.runner.module import DepthModule

    net = prior_net(folder)
    spec = {"name": "depth_anything_v2", "weights": str(folder), "input_size": 28}
    net_config = {"backbone": "resnet10t", "fusion": "concat", "prior": {**spec, "dropout": 0.2}}
    checkpoint = {"state_dict": {f"net.{k}": v for k, v in net.state_dict().items()}}
    module = DepthModule(net)
    module.run_config = {
        "model": {"net": net_config},
        "fusion": {"mode": "concat"},
        "backbone": {"name": "resnet10t"},
        "dataset": DATASET,
    }
    module.on_save_checkpoint(checkpoint)
    torch.save(checkpoint, path)
    return path


def test_a_checkpoint_refuses_a_prior_replaced_at_its_path(tmp_path, tiny_folder, caplog):
    from fusion_depth.runner.checkpoints import load_model
    from fusion_depth.utils.checkpoint_file import CheckpointError

    folder = tmp_path / "weights"
    shutil.copytree(tiny_folder, folder)
    path = _checkpoint_with_prior(tmp_path / "net.ckpt", folder)
    assert load_model(path).net.prior is not None
    copy = tmp_path / "copy"  # the same weights elsewhere: the same prior
    shutil.copytree(folder, copy)
    load_model(path, prior={"name": "depth_anything_v2", "weights": str(copy)})
    # Another network saved to the same place (a re-download, another size)
    torch.manual_seed(1)
    other = tiny_depth_anything()
    with torch.no_grad():
        for parameter in other.parameters():
            parameter.add_(0.1)
    other.save_pretrained(folder)
    with pytest.raises(CheckpointError) as raised:
        load_model(path)
    from fusion_depth.models.depth_prior import PRIOR_KEY, weights_digest

    message = str(raised.value)
    recorded = torch.load(path, weights_only=True)[PRIOR_KEY]["sha256"]
    assert message.startswith(f"ckpt_path={path}: ")
    assert recorded[:16] in message and weights_digest(folder)[:16] in message
    assert str(folder) in message and "\n" not in message
    # A resumed run (Lightning loads the checkpoint into the module) is refused the same way.
    from fusion_depth.runner.module import DepthModule

    with pytest.raises(CheckpointError, match=recorded[:16]):
        DepthModule(prior_net(folder)).on_load_checkpoint(torch.load(path, weights_only=True))
    # A checkpoint from before digests were recorded still loads, with a warning.
    old = torch.load(path, weights_only=True)
    del old[PRIOR_KEY]
    torch.save(old, tmp_path / "old.ckpt")
    with caplog.at_level("WARNING"):
        load_model(tmp_path / "old.ckpt")
    assert "records no digest of its prior" in caplog.text


@pytest.mark.slow
def test_evaluate_predict_and_export_refuse_a_replaced_prior(tmp_path, tiny_folder):
    from helpers import run_module

    folder = tmp_path / "weights"
    shutil.copytree(tiny_folder, folder)
    run = tmp_path / "run"
    prior = ["prior=depth_anything_v2", f"prior.weights={folder}", "prior.input_size=28"]
    done = _train(tmp_path, *prior, f"hydra.run.dir={run}")
    assert done.returncode == 0, done.stderr[-2000:]
    (checkpoint,) = (run / "checkpoints").glob("epoch*.ckpt")
    torch.manual_seed(1)
    tiny_depth_anything(necks=(3, 3)).save_pretrained(folder)  # another prior, same place
    commands = {
        "evaluate": ["fusion_depth.evaluate", f"ckpt_path={checkpoint}"],
        "predict": ["fusion_depth.predict", f"ckpt_path={checkpoint}", "input=split:test"],
        "export": ["fusion_depth.export", f"ckpt_path={checkpoint}", "format=onnx"],
    }
    for name, command in commands.items():
        refused = run_module(
            [*command, f"hydra.run.dir={tmp_path / name}"], cwd=tmp_path, env=offline_environment()
        )
        assert refused.returncode == 1, (name, refused.stderr[-2000:])
        lines = [line for line in refused.stderr.splitlines() if "sha256" in line]
        assert len(lines) == 1 and str(folder) in lines[0], (name, refused.stderr[-2000:])
        assert "Traceback" not in refused.stderr


def test_run_folders_name_prior_weights_short_and_stable(tmp_path):
    from fusion_depth.config.run_dirs import run_dir, run_dirname

    weights = tmp_path / "some" / "deep" / "place" / "da2-small"
    name = run_dirname(f"prior=depth_anything_v2,prior.weights={weights},seed=1")
    assert str(tmp_path.name) not in name and "_some_deep_place" not in name
    assert name.startswith("prior-depth_anything_v2+prior.weights-da2-small-")
    assert name.endswith("+seed-1") and len(name) < 70
    assert name == run_dirname(f"prior=depth_anything_v2,prior.weights={weights},seed=1")
    other = tmp_path / "elsewhere" / "da2-small"  # the same folder name, another folder
    assert run_dirname(f"prior=depth_anything_v2,prior.weights={other},seed=1") != name
    # A sweep over two weights names each short; a folder an earlier release named after the
    # whole path is still found (its run resumes).
    sweep = run_dirname(f"prior.weights={weights},{other}")
    assert sweep.count("da2-small-") == 2 and "_some_" not in sweep
    overrides = f"prior.weights={weights}"
    earlier = tmp_path / "outputs" / f"prior.weights-{str(weights).replace('/', '_')}"
    earlier.mkdir(parents=True)
    assert run_dir(str(tmp_path / "outputs"), overrides) == str(earlier)


def test_a_zero_prior_reads_no_file_and_gives_the_branch_nothing():
    """prior=zero, the control of a prior used as an input: the branch and its parameters,
    and zeros through it."""
    from fusion_depth.models import DepthNet
    from fusion_depth.models.depth_prior import ZeroPrior

    net = DepthNet(backbone="resnet10t", fusion="concat", prior={"name": "zero"}).eval()
    assert isinstance(net.prior, ZeroPrior) and net.prior_branch is not None
    image = torch.rand(2, 3, 64, 96)
    assert net.prior_input(image).abs().max() == 0
    with pytest.raises(ArgumentError, match=r"^weights=/some/file: prior=zero reads no file"):
        build_prior("zero", "/some/file")


def _association_checkpoint(path):
    """A model=radarnet stage=association checkpoint as train writes it (weights, run config)."""
    from fusion_depth.models.radarnet import RadarNet

    torch.manual_seed(3)
    net = RadarNet(stage="association")
    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    config = {"model": {"net": {"name": "radarnet", "stage": "association"}}}
    torch.save({"state_dict": state, "fusion_depth_config": config}, path)
    return path, net


def test_the_correction_takes_its_quasi_dense_map_from_a_radarnet_association(tmp_path):
    from fusion_depth.models import create_model

    path, association = _association_checkpoint(tmp_path / "association.ckpt")
    prior = {"name": "zero"}  # any relative prior: the quasi-dense map is what is checked
    net = create_model(
        "prior_correction",
        prior=prior,
        quasi_dense="association",
        association_weights=str(path),
    ).eval()
    for key, value in association.association.state_dict().items():
        torch.testing.assert_close(net.association.association.state_dict()[key], value)
    assert not any(p.requires_grad for p in net.association.parameters())  # frozen
    image = torch.rand(1, 3, 64, 96)
    sparse = torch.zeros(1, 1, 64, 96)
    points = torch.zeros(1, 4, 6)
    points[0, :, 0] = torch.tensor([10.0, 40.0, 60.0, 90.0])
    points[0, :, 1] = 40.0
    points[0, :, 2] = torch.tensor([5.0, 12.0, 20.0, 33.0])
    points[0, :, 5] = 1.0
    association.eval()
    with torch.no_grad():
        expected = association(image, sparse, points)
    torch.testing.assert_close(net.quasi_dense_depth(image, sparse, points), expected)
    net.train()
    assert not net.association.training  # its batch norms keep their statistics
    # Rebuilt from its own checkpoint (no association_weights): the weights come with its state.
    again = create_model("prior_correction", prior=prior, quasi_dense="association")
    again.load_state_dict(net.state_dict())
    torch.testing.assert_close(again.eval().quasi_dense_depth(image, sparse, points), expected)
    untrained = create_model("prior_correction", prior=prior, quasi_dense="association")
    with pytest.raises(ArgumentError, match=r"^quasi_dense=association needs a trained"):
        untrained.quasi_dense_depth(image, sparse, points)
    with pytest.raises(ArgumentError, match=r"^quasi_dense='lidar': expected one of"):
        create_model("prior_correction", prior=prior, quasi_dense="lidar")
