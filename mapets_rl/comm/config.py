"""Communication settings of range-limited data sharing (MA-PETS sec. IV-C)."""

from __future__ import annotations

import dataclasses

from mapets_rl.config import ConfigSection, check

__all__ = ["CommConfig"]


@dataclasses.dataclass(frozen=True)
class CommConfig(ConfigSection):
    """Who receives whose transitions.

    Attributes:
        comm_range: communication range ``d`` in metres (``0``: independent learners,
            ``inf``: everybody shares); paper: 100.
        p_fail: probability that a communication link fails, in ``[0, 1]``.
        share_plans: every step each CAV also broadcasts the speeds its chosen plan predicts,
            and the CAVs that hear it plan with them as that neighbour's future speeds
            (:mod:`mapets_rl.comm.plans`; off: the paper's MA-PETS).
    """

    comm_range: float = dataclasses.field(default=100.0, metadata={"allow_inf": True, "unit": "m"})
    p_fail: float = 0.0
    share_plans: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.comm_range >= 0, "comm_range", ">= 0 metres (inf allowed)", self.comm_range)
        check(0.0 <= self.p_fail <= 1.0, "p_fail", "in [0, 1]", self.p_fail)
