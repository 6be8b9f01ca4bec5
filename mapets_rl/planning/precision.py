"""Which floating-point type the planner's ensemble forward runs in (``dtype="auto"``).

bf16 halves the memory traffic of the MLP and runs on native instructions where the hardware
has them (CPU: AVX512-BF16 or AMX; CUDA: compute capability >= 8.0). Where it does not, torch
emulates bf16 matmuls and they are 4-20x *slower* than fp32 (measured on an AVX2-only AMD EPYC,
``docs/results/performance.md``), so ``"auto"`` falls back to fp32 there.
"""

from __future__ import annotations

import functools

import torch

from mapets_rl.config import check

__all__ = ["DTYPE_CHOICES", "cpu_bf16_flags", "resolve_dtype"]

#: Accepted values of ``PlannerConfig.dtype`` / ``TrajectorySamplingCEM(dtype=...)``.
DTYPE_CHOICES = ("auto", "fp32", "bf16")
_NAMED = {"fp32": torch.float32, "bf16": torch.bfloat16}


@functools.cache
def cpu_bf16_flags() -> tuple[str, ...]:
    """The native-bf16 CPU features present: a subset of ``("avx512_bf16", "amx_bf16")``.

    Asks torch's own cpuinfo probes (the ones its oneDNN kernels dispatch on) and, where those
    are missing, the ``/proc/cpuinfo`` flags.
    """
    found: set[str] = set()
    probes = {"avx512_bf16": "_is_avx512_bf16_supported", "amx_bf16": "_is_amx_tile_supported"}
    for flag, name in probes.items():
        probe = getattr(torch.cpu, name, None)
        if probe is not None and probe():
            found.add(flag)
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    found.update(set(line.split()) & set(probes))
                    break
    except OSError:
        pass
    return tuple(sorted(found))


def resolve_dtype(
    dtype: str | torch.dtype = "auto", device: torch.device | str = "cpu"
) -> tuple[torch.dtype, str]:
    """The compute dtype of the planner's ensemble forward, and why it was chosen.

    Args:
        dtype: ``"auto"``, ``"fp32"``, ``"bf16"``, ``torch.float32`` or ``torch.bfloat16``.
            ``"auto"`` picks bf16 on a CUDA device that supports it and on a CPU with
            AVX512-BF16 or AMX, fp32 everywhere else.
        device: where the model runs.

    Returns:
        ``(torch dtype, one-line reason)``.

    Raises:
        ConfigError: ``dtype`` is not one of the accepted values (named ``dtype``).
    """
    if isinstance(dtype, torch.dtype):
        check(dtype in _NAMED.values(), "dtype", "torch.float32 or torch.bfloat16", dtype)
        return dtype, f"{dtype} requested"
    check(dtype in DTYPE_CHOICES, "dtype", f"one of {list(DTYPE_CHOICES)}", dtype)
    if dtype != "auto":
        return _NAMED[dtype], f"dtype={dtype} requested"
    device = torch.device(device)
    if device.type == "cuda":
        if torch.cuda.is_bf16_supported(including_emulation=False):
            name = torch.cuda.get_device_name(device)
            return torch.bfloat16, f"auto: bf16, {name} supports bf16 natively"
        return torch.float32, "auto: fp32, this CUDA device has no native bf16"
    if device.type != "cpu":
        return torch.float32, f"auto: fp32 on {device.type} (bf16 chosen only on cpu/cuda)"
    capability = torch.backends.cpu.get_cpu_capability()
    flags = cpu_bf16_flags()
    if flags:
        return torch.bfloat16, f"auto: bf16, CPU has {'+'.join(flags)} (capability {capability})"
    return (
        torch.float32,
        f"auto: fp32, CPU has no AVX512-BF16/AMX (capability {capability}): bf16 would be slower",
    )
