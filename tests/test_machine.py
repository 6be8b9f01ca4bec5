"""mapets_rl.machine: the line every benchmark prints names the CPU model, torch's CPU
capability (AVX2 / AVX512 decide how fast bf16 is), the torch version and the thread count."""

from __future__ import annotations

import builtins
import platform

import torch

from mapets_rl import machine


def test_the_machine_line_names_model_capability_version_and_threads() -> None:
    line = machine.machine_line()
    assert line.startswith(machine.cpu_model() + ", ")
    assert f"CPU capability {torch.backends.cpu.get_cpu_capability()}" in line
    assert f"torch {torch.__version__}" in line
    assert f"{torch.get_num_threads()} thread(s)" in line


def test_without_cpuinfo_the_model_is_what_platform_says(monkeypatch) -> None:
    real_open = builtins.open

    def no_cpuinfo(path, *args, **kwargs):
        if str(path) == "/proc/cpuinfo":
            raise OSError("not here")
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", no_cpuinfo)
    assert machine.cpu_model() == (platform.processor() or platform.machine())
