"""bfloat16 only where it is native: ``use_bf16=True`` falls back to float32 (with a warning) elsewhere.

On a CPU without bfloat16 instructions (AVX2 only) torch emulates bfloat16 autocast and a PEARL+
gradient step runs *slower* than in float32 (the figures: docs/speed.md, "Opt-in: bfloat16"). Native
support: x86 CPUs with AVX512-BF16 or AMX-BF16, Arm CPUs with the BF16 extension (``/proc/cpuinfo``
flags), CUDA devices for which ``torch.cuda.is_bf16_supported()``.
"""

from __future__ import annotations

import functools
import platform
import warnings

import torch as th

# /proc/cpuinfo flags of native bfloat16 arithmetic: x86 AVX512-BF16 / AMX-BF16, aarch64 BF16.
BF16_CPU_FLAGS = frozenset({"avx512_bf16", "amx_bf16", "bf16"})


@functools.lru_cache(maxsize=1)
def cpu_flags() -> frozenset[str]:
    """The CPU feature flags of ``/proc/cpuinfo`` (empty where there is no such file, e.g. macOS, Windows)."""
    try:
        with open("/proc/cpuinfo") as file:
            text = file.read()
    except OSError:
        return frozenset()
    flags: set[str] = set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            flags.update(value.split())
    return frozenset(flags)


def native_bf16(device: th.device) -> tuple[bool, str]:
    """
    Whether ``device`` computes in bfloat16 natively, and why (for messages).

    :param device: the model's torch device
    :return: (supported, reason)
    """
    if device.type == "cuda":
        supported = th.cuda.is_available() and th.cuda.is_bf16_supported()
        return supported, f"torch.cuda.is_bf16_supported() is {supported}"
    if device.type == "cpu":
        found = sorted(BF16_CPU_FLAGS & cpu_flags())
        if found:
            return True, f"CPU flags {found}"
        return False, f"no avx512_bf16 / amx_bf16 / bf16 flag in /proc/cpuinfo ({platform.machine() or 'unknown CPU'})"
    return False, f"no bfloat16 check for device type {device.type!r}"


def resolve_bf16(use_bf16: bool | str, device: th.device, algorithm: str) -> bool:
    """
    Whether gradient steps run under bfloat16 autocast: ``use_bf16=True`` only with native support (else a
    warning and float32), ``"force"`` always, ``False`` never.

    :param use_bf16: the model's setting
    :param device: its torch device
    :param algorithm: its name, for the warning
    :return: whether to enable bfloat16 autocast
    """
    if use_bf16 == "force":
        return True
    if not use_bf16:
        return False
    supported, reason = native_bf16(device)
    if not supported:
        warnings.warn(
            f"{algorithm}(use_bf16=True): {device} has no native bfloat16 ({reason}); emulated bfloat16 steps are "
            "1.5-18x slower than float32, so this model trains in float32. Pass use_bf16='force' to use bfloat16 anyway",
            stacklevel=3,
        )
    return supported


__all__ = ["BF16_CPU_FLAGS", "cpu_flags", "native_bf16", "resolve_bf16"]
