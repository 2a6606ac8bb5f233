"""Speed settings: precision resolution, autocast that keeps depth and loss in fp32, the NHWC
format and compilation keeping checkpoints loadable."""

from __future__ import annotations

import pytest
import torch

from fusion_depth.losses.depth_loss import DepthLoss
from fusion_depth.models import DepthNet
from fusion_depth.runner import speed
from fusion_depth.runner.module import DepthModule


def test_auto_precision_is_bf16_only_where_the_cpu_has_bf16(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(speed, "cpu_flags", lambda: {"avx2", "avx512f", "avx512_bf16"})
    assert speed.resolve_precision("auto", "cpu") == "bf16-mixed"
    monkeypatch.setattr(speed, "cpu_flags", lambda: {"avx2", "amx_bf16"})
    assert speed.resolve_precision("auto", "cpu") == "bf16-mixed"
    monkeypatch.setattr(speed, "cpu_flags", lambda: {"avx2", "avx512f"})
    assert speed.resolve_precision("auto", "cpu") == "32-true"
    assert speed.resolve_precision("32-true", "cpu") == "32-true"
    assert speed.resolve_precision("bf16-mixed", "cpu") == "bf16-mixed"  # asked for: honoured


@pytest.mark.parametrize(
    ("value", "message"),
    [("fp8", "trainer.precision='fp8': expected one of"), ("16-mixed", "needs a GPU")],
)
def test_bad_precision_is_refused_naming_the_key(value: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        speed.resolve_precision(value, "cpu")


def test_the_error_names_the_key_the_caller_reads() -> None:
    with pytest.raises(ValueError, match=r"^precision='fp8': expected one of"):
        speed.resolve_precision("fp8", "cpu", key="precision")


def test_bad_device_and_compile_values_are_refused() -> None:
    with pytest.raises(ValueError, match="device=tpu7"):
        speed.resolve_device("tpu7")
    with pytest.raises(ValueError, match="model.compile='sometimes'"):
        speed.should_compile("sometimes", "cpu")
    assert speed.should_compile("auto", "cpu") is False
    assert speed.should_compile(True, "cpu") is True


def _net(fusion: str = "rgb") -> DepthNet:
    torch.manual_seed(0)
    return DepthNet("resnet18", fusion=fusion).eval()


def test_bf16_autocast_keeps_depth_in_fp32_and_close_to_fp32() -> None:
    net = _net("concat")
    image = torch.rand(1, 3, 64, 96)
    sparse = torch.where(torch.rand(1, 1, 64, 96) < 0.05, 20.0, 0.0)
    with torch.no_grad():
        reference = net(image, sparse)  # reciprocal depth, before clipping to the depth range
        with speed.autocast("bf16-mixed", "cpu"):
            inner = net.encoder(net.fusion(image, sparse))[-1]
            reciprocal = net(image, sparse)
            depth = net.predict_depth(image, sparse)
    assert inner.dtype == torch.bfloat16  # autocast is really on inside the network
    assert reciprocal.dtype == depth.dtype == torch.float32
    scale = reference.abs().max()
    assert (reciprocal - reference).abs().max() < 0.05 * scale
    assert not torch.equal(reciprocal, reference)


def test_the_loss_is_computed_in_fp32_under_autocast() -> None:
    module = DepthModule(_net(), loss=DepthLoss(max_val=20.0)).train()
    batch = {
        "image": torch.rand(2, 3, 64, 96),
        "sparse": torch.zeros(2, 1, 64, 96),
        "depth": 1 + 50 * torch.rand(2, 1, 64, 96),
    }
    reference = module.step_losses(batch)
    with speed.autocast("bf16-mixed", "cpu"):
        mixed = module.step_losses(batch)
    for key, value in mixed.items():
        assert value.dtype == torch.float32, key
        assert value.item() == pytest.approx(reference[key].item(), rel=0.05), key


def test_channels_last_and_compile_keep_the_checkpoint_keys() -> None:
    net = _net()
    keys = list(net.state_dict())
    speed.speed_up(net, channels_last=True, compile=True, device="cpu")
    conv = net.encoder.stages["conv1"].weight
    assert conv.is_contiguous(memory_format=torch.channels_last) and not conv.is_contiguous()
    assert net._compiled_call_impl is not None
    assert list(net.state_dict()) == keys  # no "_orig_mod." prefix: checkpoints stay loadable
    speed.speed_up(net, channels_last=False, compile=False, device="cpu")  # leaves it as it is
    assert net._compiled_call_impl is not None


def test_channels_last_gives_the_same_depth() -> None:
    net = _net("add")
    image = torch.rand(2, 3, 64, 96)
    sparse = torch.where(torch.rand(2, 1, 64, 96) < 0.05, 30.0, 0.0)
    with torch.no_grad():
        reference = net.predict_depth(image, sparse)
        speed.speed_up(net, channels_last=True, compile=False, device="cpu")
        assert torch.allclose(net.predict_depth(image, sparse), reference, atol=1e-4)


def test_loader_defaults_use_workers_and_pinned_memory_only_with_a_gpu(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from fusion_depth.runner.datamodule import DepthDataModule

    # The cores this process may use (a SLURM job's share, not the whole node's).
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: set(range(16)))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    gpu = DepthDataModule(reader=lambda split: [])
    assert (gpu.num_workers, gpu.pin_memory, gpu.persistent_workers) == (8, True, True)
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1, 2, 3})
    assert DepthDataModule(reader=lambda split: []).num_workers == 3
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cpu = DepthDataModule(reader=lambda split: [])
    assert (cpu.num_workers, cpu.pin_memory, cpu.persistent_workers) == (0, False, False)
    assert DepthDataModule(reader=lambda split: [], num_workers=3).num_workers == 3
    with pytest.raises(ValueError, match="data.num_workers='many'"):
        DepthDataModule(reader=lambda split: [], num_workers="many")


def test_evaluate_scores_in_the_checkpoints_precision_by_default(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from types import SimpleNamespace

    from fusion_depth.evaluate.scoring import evaluation_precision

    monkeypatch.setattr(speed, "cpu_flags", lambda: {"avx512_bf16"})
    fp32 = SimpleNamespace(config={"trainer": {"precision": "32-true"}})
    bf16 = SimpleNamespace(config={"trainer": {"precision": "bf16-mixed"}})
    unknown = SimpleNamespace(config={})
    gpu_fp16 = SimpleNamespace(config={"trainer": {"precision": "16-mixed"}})
    assert evaluation_precision("checkpoint", fp32, "cpu") == "32-true"
    assert evaluation_precision("checkpoint", bf16, "cpu") == "bf16-mixed"
    assert evaluation_precision("checkpoint", unknown, "cpu") == "bf16-mixed"  # auto
    assert evaluation_precision("checkpoint", gpu_fp16, "cpu") == "bf16-mixed"  # auto
    assert evaluation_precision("32-true", bf16, "cpu") == "32-true"  # asked for: honoured
