"""The scene's MuJoCo model: ``assets/scene.xml``, and what a task or an option adds to it."""

from __future__ import annotations

from pathlib import Path

import mujoco

from lerobot_suture.sim.appearance import add_tissue_texture
from lerobot_suture.sim.running_suture import add_suture_marks
from lerobot_suture.sim.wrist_camera import add_wrist_camera

SCENE_XML = Path(__file__).parent / "assets" / "scene.xml"


def scene_model(task: str, tissue_texture: bool = False, wrist_camera: bool = False) -> mujoco.MjModel:
    """The compiled scene: the running suture's four pairs of marks, the tissue's texture and the wrist
    camera added where asked; the XML as it is otherwise."""
    if not (tissue_texture or wrist_camera or task == "running_suture"):
        return mujoco.MjModel.from_xml_path(str(SCENE_XML))
    spec = mujoco.MjSpec.from_file(str(SCENE_XML))
    if tissue_texture:
        add_tissue_texture(spec)
    if task == "running_suture":
        add_suture_marks(spec)
    if wrist_camera:
        add_wrist_camera(spec)
    return spec.compile()
