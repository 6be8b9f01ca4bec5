"""The planner's optimiser is named in its config (``optimizer: cem | icem``): iCEM's fields are
refused under ``cem`` naming them, the presets choose the optimisers they chose before (paper:
CEM, cpu: iCEM), a config file written before the field reads as the optimiser its iCEM fields
chose, and MA-PETS checks the planner's own memory estimate (anchors and kept elites counted)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from mapets_rl.config import ConfigError
from mapets_rl.modules import AgentGroupSpec
from mapets_rl.planning import (
    CPU_PRESET,
    PAPER_PRESET,
    CEMOptimizer,
    ICEMOptimizer,
    PlannerConfig,
)
from mapets_rl.planning.memory import planner_bytes
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig


def test_the_presets_name_the_optimisers_they_used() -> None:
    assert (PAPER_PRESET.planner.optimizer, CPU_PRESET.planner.optimizer) == ("cem", "icem")
    assert type(PAPER_PRESET.planner.make_optimizer()) is CEMOptimizer
    assert type(CPU_PRESET.planner.make_optimizer()) is ICEMOptimizer
    assert MAPETSConfig(preset="cpu").planner.optimizer == "icem"


def test_icem_fields_under_cem_are_refused_naming_them() -> None:
    with pytest.raises(ConfigError, match="optimizer must be one of"):
        PlannerConfig(optimizer="mppi")
    with pytest.raises(
        ConfigError,
        match=r"^keep_best must be False with optimizer='cem' \(keep_best, noise_beta: iCEM's",
    ):
        PlannerConfig(keep_best=True, noise_beta=2.0)
    with pytest.raises(ConfigError, match=r"^planner\.anchor_candidates must be False"):
        MAPETSConfig().with_overrides(["planner.anchor_candidates=true"])
    config = MAPETSConfig().with_overrides(["planner.optimizer=icem", "planner.keep_best=true"])
    assert config.planner.keep_best and config.planner.optimizer == "icem"


def test_a_config_written_before_the_field_reads_as_the_optimiser_it_chose(
    tmp_path: Path,
) -> None:
    assert PlannerConfig.upgrade_dict({"keep_best": True})["optimizer"] == "icem"
    assert "optimizer" not in PlannerConfig.upgrade_dict({"keep_best": False, "horizon": 5})
    assert PlannerConfig.upgrade_dict({"optimizer": "cem"}) == {"optimizer": "cem"}
    for preset in ("cpu", "paper"):
        written = MAPETSConfig(preset=preset).to_dict()
        del written["planner"]["optimizer"]  # as config.yaml files were written before it
        path = tmp_path / f"{preset}.yaml"
        path.write_text(yaml.safe_dump(written))
        read = MAPETSConfig.from_yaml(path)
        assert read.planner == MAPETSConfig(preset=preset).planner


def test_mapets_checks_the_planners_memory_estimate(monkeypatch: pytest.MonkeyPatch) -> None:
    planner = CPU_PRESET.planner  # 8 sampled candidates + 3 anchors scored per iteration
    dims = (4, 10, 1)
    assert planner.decision_bytes(*dims, [64]) == planner_bytes(*dims, (64,), 11, 5, 25)
    monkeypatch.setattr(PlannerConfig, "decision_bytes", lambda self, *args: 2**62)
    group = AgentGroupSpec(n_agents=4, obs_dim=10, action_dim=1, discrete=False, action_spec=None)
    with pytest.raises(ValueError, match="the planner, ensembles and datasets need about"):
        MAPETS._check_scenario(MAPETSConfig(preset="cpu"), group, lambda *a: torch.zeros(()))
