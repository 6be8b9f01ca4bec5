"""benchmarks/cooperation_control.py: its arms are published configurations, trained and scored
by the library (``tests/experiment/test_protocol.py``, ``test_published_configs.py``); a name
that is not one is refused before any run starts."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from mapets_rl.config import ConfigError


def test_an_unknown_config_is_refused_first(load_script: Callable, tmp_path: Path) -> None:
    control = load_script("benchmarks/cooperation_control.py")
    argv = ["--configs", "freeway-merge/maddpg-individual", "freeway-merge/no-such-arm"]
    with pytest.raises(ConfigError, match="no-such-arm"):
        control.main([*argv, "--seeds", "0", "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()
