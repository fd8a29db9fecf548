"""LeRobot policy plugin `suture_chain`: the running suture's high level above one policy per subtask.

Importing the package registers `SutureChainConfig` as policy type "suture_chain" (LeRobot imports installed
`lerobot_policy_*` distributions on start); the policy is imported on first use.
"""

from .configuration_suture_chain import SutureChainConfig

__all__ = ["SutureChainConfig"]
