"""Size and training hyper-parameters of the MA-PETS probabilistic ensembles."""

from __future__ import annotations

import dataclasses

from mapets_rl.config import ConfigSection, check

__all__ = ["EnsembleConfig"]


@dataclasses.dataclass(frozen=True)
class EnsembleConfig(ConfigSection):
    """The CAVs' probabilistic ensembles and how they are trained (defaults: the paper's
    Table II).

    Attributes:
        ensemble_size: members ``B`` per CAV (>= 1).
        hidden: hidden layer widths of each member MLP (non-empty, each >= 1).
        epochs: training passes over ``D(i)+`` after each episode (>= 1; paper: 5); with
            ``holdout > 0`` the most that run.
        batch_size: training minibatch rows (>= 1; paper: 128).
        lr: Adam learning rate (> 0; paper: 1e-3).
        buffer_size: capacity of each CAV's dataset ``D(i)+`` in transitions (>= 1; paper:
            2048).
        logvar_bound_coef: weight of the PETS log-variance bound penalty (>= 0).
        share_model: one set of ``B`` MLPs for all CAVs (a centralised model; each CAV still
            normalises with its own statistics) instead of one ensemble per CAV.
        holdout: early stopping: the fraction of each CAV's ``D(i)+`` held out of the
            training to evaluate the ensemble's NLL after each epoch, in ``[0, 0.5)``; ``0``
            (default) is off: every refit runs all ``epochs`` on all transitions. See
            :func:`~mapets_rl.objectives.fit_ensemble`.
        patience: with ``holdout > 0``, the refit stops after this many epochs in a row in
            which no member's held-out NLL improved by more than ``min_improvement``; each
            member keeps its best weights (>= 1).
        min_improvement: relative held-out NLL improvement that counts for ``patience``
            (``(best - nll) > min_improvement * |best|``), in ``[0, 1)``.
    """

    ensemble_size: int = 5
    hidden: list[int] = dataclasses.field(default_factory=lambda: [300, 300, 300])
    epochs: int = dataclasses.field(default=5, metadata={"unit": "passes per episode"})
    batch_size: int = dataclasses.field(default=128, metadata={"unit": "transitions"})
    lr: float = 1e-3
    buffer_size: int = dataclasses.field(default=2048, metadata={"unit": "transitions per CAV"})
    logvar_bound_coef: float = 0.01
    share_model: bool = False
    holdout: float = dataclasses.field(default=0.0, metadata={"unit": "fraction of D(i)+"})
    patience: int = dataclasses.field(default=5, metadata={"unit": "epochs"})
    min_improvement: float = 0.01

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.ensemble_size >= 1, "ensemble_size", ">= 1", self.ensemble_size)
        check(
            len(self.hidden) > 0 and all(h >= 1 for h in self.hidden),
            "hidden",
            "a non-empty list of ints >= 1",
            self.hidden,
        )
        check(self.epochs >= 1, "epochs", ">= 1", self.epochs)
        check(self.batch_size >= 1, "batch_size", ">= 1", self.batch_size)
        check(self.lr > 0, "lr", "> 0", self.lr)
        check(self.buffer_size >= 1, "buffer_size", ">= 1", self.buffer_size)
        check(self.logvar_bound_coef >= 0, "logvar_bound_coef", ">= 0", self.logvar_bound_coef)
        check(0 <= self.holdout < 0.5, "holdout", "in [0, 0.5) (0: off)", self.holdout)
        check(self.patience >= 1, "patience", ">= 1", self.patience)
        check(0 <= self.min_improvement < 1, "min_improvement", "in [0, 1)", self.min_improvement)

    def model_kwargs(self) -> dict:
        """Keyword arguments for :class:`~mapets_rl.models.ProbabilisticEnsemble` (sizes and
        ``share_across_agents``)."""
        return {
            "ensemble_size": self.ensemble_size,
            "hidden": tuple(self.hidden),
            "share_across_agents": self.share_model,
        }
