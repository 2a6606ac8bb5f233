"""Speed settings shared by training, evaluation, prediction and the benchmark: the device, the
numeric precision (``trainer.precision``), the memory format (``model.channels_last``) and
compilation (``model.compile``).

``precision=auto`` picks bf16 autocast where the hardware computes in bf16 natively (GPUs of
compute capability ≥ 8.0; CPUs with AVX-512 BF16 or AMX) and fp32 elsewhere: on a CPU without
bf16 instructions autocast emulates it and is *slower* than fp32.
"""

from __future__ import annotations

import contextlib
import os
import platform
from collections.abc import Iterator
from typing import Any

import torch
from torch import nn

from fusion_depth.utils.schema import BOOLEAN, Schema, one_of

# Lightning's precision names that this platform supports, plus "auto" (resolved here).
PRECISIONS = ("auto", "32-true", "bf16-mixed", "16-mixed")
_AUTOCAST_DTYPES = {"bf16-mixed": torch.bfloat16, "16-mixed": torch.float16}
# /proc/cpuinfo flags of native bf16 arithmetic (x86: AVX-512 BF16, AMX; Arm: BF16 extension).
_CPU_BF16_FLAGS = {"avx512_bf16", "amx_bf16", "bf16"}


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` (CUDA when available), ``cpu``, ``cuda`` or ``cuda:<index>`` → a device."""
    name = str(name)
    if name in ("auto", "gpu"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ValueError(
            f"device={name}: expected auto, cpu, cuda or cuda:<index> ({err})"
        ) from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={name}: CUDA is not available here; use device=cpu or auto")
    return device


def accelerator_device(accelerator: str) -> torch.device:
    """The device a Lightning ``trainer.accelerator`` value trains on (single device)."""
    return resolve_device("cuda" if accelerator in ("cuda", "gpu") else accelerator)


def cpu_flags() -> set[str]:
    """The CPU's feature flags from /proc/cpuinfo (empty where that file does not exist)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo where it exists)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def supports_bf16(device: torch.device | str) -> bool:
    """Whether ``device`` computes bf16 natively (so bf16 autocast is a speed-up there)."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported(including_emulation=False)
    if device.type == "cpu":
        return bool(cpu_flags() & _CPU_BF16_FLAGS)
    return False


def resolve_precision(
    precision: str, device: torch.device | str, key: str = "trainer.precision"
) -> str:
    """``auto`` → ``bf16-mixed`` where :func:`supports_bf16`, else ``32-true``; others checked.
    ``key`` is the config key errors name."""
    precision = str(precision)
    if precision not in PRECISIONS:
        raise ValueError(f"{key}={precision!r}: expected one of {list(PRECISIONS)}")
    device = torch.device(device)
    if precision == "auto":
        return "bf16-mixed" if supports_bf16(device) else "32-true"
    if precision == "16-mixed" and device.type != "cuda":
        raise ValueError(
            f"{key}=16-mixed: fp16 autocast needs a GPU; use bf16-mixed or 32-true on a CPU"
        )
    return precision


@contextlib.contextmanager
def autocast(precision: str, device: torch.device | str) -> Iterator[None]:
    """Autocast for a resolved ``precision`` on ``device`` (nothing for ``32-true``), the way
    Lightning's mixed-precision plugin runs the steps, for code outside a Trainer."""
    dtype = _AUTOCAST_DTYPES.get(precision)
    if dtype is None:
        yield
        return
    with torch.autocast(device_type=torch.device(device).type, dtype=dtype):
        yield


def should_compile(compile: bool | str, device: torch.device | str) -> bool:
    """``model.compile``: true, false, or ``auto`` (on GPUs only: on a CPU the minutes of
    compilation outweigh what a short run gains; see docs/results/speed.md)."""
    if isinstance(compile, str):
        if compile != "auto":
            raise ValueError(f"model.compile={compile!r}: expected true, false or auto")
        return torch.device(device).type == "cuda"
    return bool(compile)


COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


def speed_up(
    net: nn.Module,
    channels_last: bool,
    compile: bool | str,
    device: torch.device | str,
    compile_mode: str = "default",
) -> nn.Module:
    """Channels-last weights (convolutions then run in NHWC, which oneDNN and cuDNN's tensor
    cores prefer; activations follow the weights' format) and in-place ``torch.compile`` of the
    forward in ``compile_mode`` (``reduce-overhead`` adds CUDA graphs, which is what batch-1
    latency on a GPU needs), keeping the module's state-dict keys. Returns ``net``."""
    if compile_mode not in COMPILE_MODES:
        raise ValueError(
            f"model.compile_mode={compile_mode!r}: expected one of {list(COMPILE_MODES)}"
        )
    if channels_last:
        net.to(memory_format=torch.channels_last)
    if should_compile(compile, device) and not getattr(net, "_compiled_call_impl", None):
        net.compile(mode=None if compile_mode == "default" else compile_mode)
    return net


def machine_info(device: torch.device | str) -> dict[str, Any]:
    """What a benchmark ran on, so numbers from different machines can be compared."""
    device = torch.device(device)
    info: dict[str, Any] = {
        "cpu": cpu_model(),
        "cpu_cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "platform": platform.platform(),
        "cpu_bf16": supports_bf16("cpu"),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
    }
    if device.type == "cuda":
        info["gpu_bf16"] = supports_bf16(device)
        info["cuda"] = torch.version.cuda
    return info


# The speed settings' values (fusion_depth.utils.schema).
CONFIG_SCHEMA: Schema = {
    "trainer.precision": one_of(*PRECISIONS),
    "model.compile": one_of(True, False, "auto"),
    "model.compile_mode": one_of(*COMPILE_MODES),
    "model.channels_last": BOOLEAN,
}
