"""What machine a measurement ran on: one line for every benchmark's output.

Timings are compared only within one run on one machine, and machines of the same kind differ
by CPU (AVX2-only against AVX512-BF16: bf16 is 3.3x faster on one and much slower on the
other), so every benchmark prints :func:`machine_line` first.
"""

from __future__ import annotations

import platform

import torch

__all__ = ["cpu_model", "machine_line"]


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what :mod:`platform` says."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_line() -> str:
    """``"<CPU model>, CPU capability <AVX2|AVX512|...>, torch <version>, <n> thread(s)"``
    (and the GPU's name where CUDA is available)."""
    parts = [
        cpu_model(),
        f"CPU capability {torch.backends.cpu.get_cpu_capability()}",
        f"torch {torch.__version__}",
        f"{torch.get_num_threads()} thread(s)",
    ]
    if torch.cuda.is_available():
        parts.append(f"GPU {torch.cuda.get_device_name()}")
    return ", ".join(parts)
