"""mapets_rl: multi-agent reinforcement learning for connected autonomous vehicles on TorchRL."""

__version__ = "0.1.0"
