"""mapets_rl: multi-agent reinforcement learning for connected autonomous vehicles on TorchRL."""

from mapets_rl._console import quiet_dependencies

__version__ = "0.1.0"

quiet_dependencies()
