"""The runtime layer: what every command that runs a policy or the expert shares.

- :mod:`~lerobot_suture.runtime.config`: the base config of every command that runs a trained policy;
- :mod:`~lerobot_suture.runtime.policy`: loading a policy through LeRobot's factory, and the runner that
  acts for one env or a batch, with the O.O.D. gate's mode (report or enforce) passed to it;
- :mod:`~lerobot_suture.runtime.rollout`: policy rollouts with the gate and the surgeon stand-in;
- :mod:`~lerobot_suture.runtime.expert_rollout`: rollouts of the scripted expert;
- :mod:`~lerobot_suture.runtime.seeds`: the episode seeds of every group of runs;
- :mod:`~lerobot_suture.runtime.calibration`: fitting the gate on nominal rollouts;
- :mod:`~lerobot_suture.runtime.training`: training with the real ``lerobot-train``, resumable.

Commands (:mod:`lerobot_suture.commands`) sit above it; the sim, safety, datasets and detectors
packages sit below it and never import it.
"""
