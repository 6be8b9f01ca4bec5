"""mapets_rl: multi-agent reinforcement learning for connected autonomous vehicles on TorchRL.

Importing the package changes no global state (logging handlers, warning filters): the
``mapets-rl`` command and the example scripts call :func:`quiet_dependencies` themselves; a
library user may too.
"""

from mapets_rl._console import quiet_dependencies

__version__ = "0.1.0"

__all__ = ["quiet_dependencies"]
