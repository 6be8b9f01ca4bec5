"""The freeway scenarios (``freeway``, ``freeway-merge``) as one batched tensor program.

``make_env(name, backend="torch", num_envs=B)`` returns :class:`TorchFreewayEnv`: ``B``
independent roads stepped together on a CPU or a GPU, with highway-env's drivers (IDM, MOBIL,
its lateral controller and kinematics) reproduced in tensors (:mod:`.dynamics`) and calibrated
against the highway-env scenarios, which stay the reference (:mod:`.highway_state` moves a scene
from one to the other).
"""
