"""Safety layers: the model-free control barrier function (``cbf`` and ``surface_cbf``, the math; ``cbf_config``;
``tip_guard``, the guard over the union of the space above the tissue and the wound, with ``wound`` and
``wound_motion``; ``cbf_wrapper``, the env path; ``cbf_replay``) and the out-of-distribution gate (``ood``).

The CBF names are re-exported here; ``cbf_replay`` (matplotlib) and ``ood`` are imported from their
modules.
"""

from lerobot_suture.safety.cbf import (
    CBFResult,
    ellipsoid_grad_h,
    ellipsoid_h,
    filter_velocity,
    filter_velocity_discrete,
    inward_normal,
    margin_level,
    suture_ellipsoid_frame,
)
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.cbf_wrapper import CBFActionWrapper

__all__ = [
    "CBFActionWrapper",
    "CBFConfig",
    "CBFResult",
    "ellipsoid_grad_h",
    "ellipsoid_h",
    "filter_velocity",
    "filter_velocity_discrete",
    "inward_normal",
    "margin_level",
    "suture_ellipsoid_frame",
]
