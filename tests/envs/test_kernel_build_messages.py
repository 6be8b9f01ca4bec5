"""The batched freeway's C++ step kernel says when it is built (and how long that may take) and
when the simulator falls back to its torch program, on the ``mapets_rl`` loggers that the
``mapets-rl`` command prints; a cached build of this checkout's source is loaded silently."""

from __future__ import annotations

import logging
import os
import types
from pathlib import Path

import pytest
import torch.utils.cpp_extension

from mapets_rl.envs.torch_freeway import native


def _built(directory: Path, source: Path) -> None:
    (directory / "build.ninja").write_text(f"build native_step.o: compile {source}\n")
    (directory / f"{native.NAME}.so").write_bytes(b"")


def test_needs_build_unless_this_checkouts_source_was_built_after_its_last_change(
    tmp_path: Path,
) -> None:
    assert native.needs_build(tmp_path)  # nothing built
    _built(tmp_path, native.SOURCE)
    assert not native.needs_build(tmp_path)
    old = native.SOURCE.stat().st_mtime - 60
    os.utime(tmp_path / f"{native.NAME}.so", (old, old))
    assert native.needs_build(tmp_path)  # the source changed since
    _built(tmp_path, Path("/elsewhere/native_step.cpp"))
    assert native.needs_build(tmp_path)  # another checkout's build


@pytest.fixture
def fresh_kernel(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """A process that has not loaded the kernel, building into ``tmp_path``."""
    monkeypatch.setattr(native, "_KERNEL", None)
    monkeypatch.setattr(native, "_FAILURE", None)
    monkeypatch.setattr(native, "build_directory", lambda: tmp_path)
    return tmp_path


def test_a_build_is_announced_with_its_duration(
    fresh_kernel: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    module = types.ModuleType(native.NAME)
    monkeypatch.setattr(torch.utils.cpp_extension, "load", lambda **kwargs: module)
    with caplog.at_level(logging.INFO, logger="mapets_rl"):
        assert native.load_kernel() is module
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and warnings[0].name.startswith("mapets_rl.")
    assert "building the batched freeway's C++ step kernel" in warnings[0].getMessage()
    assert "35 s to 6 minutes" in warnings[0].getMessage()
    assert any("built in" in r.getMessage() for r in caplog.records)


def test_a_cached_build_loads_without_a_word(
    fresh_kernel: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    _built(fresh_kernel, native.SOURCE)
    module = types.ModuleType(native.NAME)
    monkeypatch.setattr(torch.utils.cpp_extension, "load", lambda **kwargs: module)
    with caplog.at_level(logging.INFO, logger="mapets_rl"):
        assert native.load_kernel() is module
    assert not caplog.records


def test_the_fallback_to_the_torch_program_is_announced(
    fresh_kernel: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def no_compiler(**kwargs: object) -> types.ModuleType:
        raise OSError("no C++ compiler (test)")

    monkeypatch.setattr(torch.utils.cpp_extension, "load", no_compiler)
    with caplog.at_level(logging.WARNING, logger="mapets_rl"):
        assert native.load_kernel() is None
    messages = [r.getMessage() for r in caplog.records]
    assert "building" in messages[0]
    assert "no C++ compiler (test)" in messages[1] and "torch program instead" in messages[1]
    assert native.kernel_unavailable() == "OSError: no C++ compiler (test)"
