"""Without the extra ``mapets-rl[sumo]``, ``backend="sumo"`` fails at once with one line naming
the extra to install (runs everywhere: SUMO's absence is simulated)."""

from __future__ import annotations

import sys

import pytest

from mapets_rl.envs import make_env


@pytest.mark.parametrize("module", ["libsumo", "traci", "sumo"])
def test_missing_extra_named_in_one_line(monkeypatch, module: str) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # import of it raises ImportError
    with pytest.raises(ImportError) as raised:
        make_env("figure-eight", backend="sumo")
    message = str(raised.value)
    assert "pip install 'mapets-rl[sumo]'" in message and "\n" not in message
    # before any work: even a config the scenario would refuse gets the same answer first
    with pytest.raises(ImportError, match=r"mapets-rl\[sumo\]"):
        make_env("figure-eight", backend="sumo", lanes=7, no_such_key=1)
