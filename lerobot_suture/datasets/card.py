"""The dataset card (``README.md``) of a recorded dataset, from ``recipes/card_template.md``.

Our template renders the card's description; LeRobot's own card builder
(``lerobot.datasets.utils.create_lerobot_dataset_card``, the one ``LeRobotDataset.push_to_hub`` uses)
wraps it with the YAML header (license, tags, ``task_categories``), the LeRobot badge, the
``meta/info.json`` structure and the citation. ``write_dataset_card`` saves the same card locally that
``push_to_hub`` uploads, so what a user reads offline is what the Hub shows.
"""

from __future__ import annotations

import math
from pathlib import Path

from lerobot_suture.datasets import metadata

PAPER_TITLE = "Safe Uncertainty-Aware Learning of Robotic Suturing"
PAPER_URL = "https://arxiv.org/abs/2505.16596"
CITATION_BIBTEX = """@article{empleo2025safe,
  title   = {Safe Uncertainty-Aware Learning of Robotic Suturing},
  author  = {Empleo, Wilbert Peter and Kim, Yitaek and Kim, Hansoul and
             Savarimuthu, Thiusius Rajeeth and Iturrate, I{\\~n}igo},
  journal = {arXiv preprint arXiv:2505.16596},
  year    = {2025}
}"""
HOMEPAGE: str | None = None
"""The project's home page for the card's "Homepage" line (None: LeRobot's placeholder)."""
LICENSE = "apache-2.0"
"""Hub license identifier of the recorded datasets (Apache-2.0, as the code)."""
TAGS = ["lerobot-suture", "surgical-robotics", "suturing", "needle-insertion", "simulation", "mujoco"]
"""Hub tags added to LeRobot's own ``LeRobot`` tag."""
TEMPLATE_NAME = "card_template.md"


def _env_state_shape(info: dict) -> tuple | None:
    """The shape of ``observation.environment_state`` ((18,): the privileged state); None if absent."""
    feature = info["features"].get("observation.environment_state")
    return None if feature is None else tuple(feature["shape"])


_MARKS_DESCRIPTION = (
    "the current throw's entry and exit marks (m), as a registered wound gives them (`--marks=true`)"
)
_SUBTASK_DESCRIPTION = (
    "the high level's subtask (one-hot: insert, extract, lay down, pick up) and throw, from the measured pose "
    "(`--subtask=true`)"
)
_REGRASP_TARGET_DESCRIPTION = (
    "the planned regrasp, in the jaw frame (m, rotation columns) (`--regrasp_target=true`; through the marks, or "
    "from where the jaw let go of the needle with `--regrasp_from=release`)"
)


def _env_state_parts(info: dict) -> tuple[bool, bool, bool]:
    """Whether ``observation.environment_state`` holds the wound's marks, the high level's subtask, and the
    planned regrasp."""
    feature = info["features"].get("observation.environment_state") or {}
    names = list(feature.get("names") or [])
    return "entry_x" in names, "subtask_insert" in names, "regrasp_dx" in names


_RELATIVE_ACTION_DESCRIPTION = (
    "the motion from the measured jaw-tip pose to the target at the end of the control step, in the jaw frame "
    "(`--relative_actions=true`)"
)


def _relative_actions(info: dict) -> bool:
    """Whether the dataset's actions are relative to the measured jaw pose (named ``dx`` ...)."""
    return "dx" in (info["features"].get("action", {}).get("names") or [])


_DESCRIPTIONS = {
    "observation.images.endoscope": "endoscope RGB image",
    "observation.state": "measured jaw-tip pose (pose layout below)",
    "observation.environment_state": "privileged: entry, exit, needle centre (m), needle rotation "
    "columns, needle tip (m)",
    "observation.needle_keypoints": "privileged: the needle's tip, middle and tail in the endoscope image "
    "(x right, y down, -1 to 1); a training target (`--policy.needle_keypoints_weight`), not an input",
    "action": "target jaw-tip pose at the end of the control step",
    "next.reward": "1 from the step the insertion succeeds on",
    "next.success": "the insertion succeeded after this action",
    "next.done": "the episode ended after this action",
    "timestamp": "time since the episode start (s)",
    "frame_index": "frame in the episode",
    "episode_index": "episode",
    "index": "frame in the dataset",
    "task_index": "task (one task)",
}


def default_template_path() -> Path:
    """``recipes/card_template.md`` of the lerobot-suture source tree."""
    return Path(__file__).resolve().parents[2] / "recipes" / TEMPLATE_NAME


def _index_range(indices: list[int]) -> str:
    if not indices:
        return "none"
    return f"{indices[0]}-{indices[-1]}" if len(indices) > 1 else str(indices[0])


def render_description(root: str | Path, template_path: str | Path | None = None) -> str:
    """Render the card template for the dataset at ``root`` (Markdown).

    Args:
        root: dataset root (with ``meta/info.json`` and the episode log).
        template_path: Jinja2 template; None: :func:`default_template_path`.

    Raises:
        FileNotFoundError: the template is missing (an installed wheel without the source tree).
    """
    import jinja2
    import mujoco

    from lerobot_suture.sim import geometry, task, tissue
    from lerobot_suture.sim.appearance import AppearanceConfig, ranges_table
    from lerobot_suture.sim.extraction import STRAIN_BOUND
    from lerobot_suture.sim.pickup import LIFT_HEIGHT
    from lerobot_suture.sim.scenarios import ScenarioConfig
    from lerobot_suture.sim.scene_model import SCENE_XML

    path = Path(template_path) if template_path is not None else default_template_path()
    if not path.is_file():
        raise FileNotFoundError(
            f"The dataset card template {path} is missing: run from a lerobot-suture source checkout "
            "(`pip install -e .`), or pass the template's path."
        )
    root = Path(root)
    info = metadata.read_json(root / metadata.INFO_PATH)
    log = metadata.read_episode_log(root)
    lengths = [e["length"] for e in log["episodes"]] or [0]
    reasons: dict[str, int] = {}
    for d in log["discarded"]:
        reasons[d["reason"]] = reasons.get(d["reason"], 0) + 1
    train, val = log["splits"]["train"], log["splits"]["val"]
    features = [
        {
            "key": key,
            "dtype": ft["dtype"],
            "shape": str(tuple(ft["shape"])),
            "description": "; ".join(
                text
                for text, on in zip(
                    (_MARKS_DESCRIPTION, _SUBTASK_DESCRIPTION, _REGRASP_TARGET_DESCRIPTION),
                    _env_state_parts(info),
                    strict=True,
                )
                if on
            )
            if key == "observation.environment_state" and any(_env_state_parts(info))
            else _RELATIVE_ACTION_DESCRIPTION
            if key == "action" and _relative_actions(info)
            else _DESCRIPTIONS.get(key, ""),
        }
        for key, ft in info["features"].items()
    ]
    env_kwargs = log["env_kwargs"]
    grasp = env_kwargs.get("grasp", "narrow")  # absent in logs before it existed
    grasp_angle, grasp_offset, grasp_roll = task.GRASP_RANGES[grasp]
    scenario = ScenarioConfig(name=env_kwargs["scenario"])
    appearance = AppearanceConfig.from_value(env_kwargs.get("appearance"))  # absent: all off
    model = mujoco.MjModel.from_xml_path(str(SCENE_XML))
    endoscope = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "endoscope")
    context = {
        "paper_title": PAPER_TITLE,
        "paper_url": PAPER_URL,
        "codebase_version": info["codebase_version"],
        "repo_id": log["repo_id"],
        "task": log["task"],
        "task_name": env_kwargs.get("task", "insertion"),  # absent in logs of insertion datasets
        "pickup_angle_deg": f"{math.degrees(task.GRASP_RANGES['narrow'][0]):g}",
        "pickup_offset_mm": f"{task.GRASP_RANGES['narrow'][1] * 1e3:g}",
        "pickup_roll_rad": f"{task.GRASP_RANGES['narrow'][2]:g}",
        "lift_height_mm": f"{LIFT_HEIGHT * 1e3:g}",
        "extraction_strain_mm": f"{STRAIN_BOUND * 1e3:g}",
        "fps": log["fps"],
        "gym_id": log["gym_id"],
        "max_episode_steps": log["max_episode_steps"],
        "obs_type": env_kwargs["obs_type"],
        "image_size": env_kwargs["image_size"],
        "scenario": env_kwargs["scenario"],
        "scenario_onset_step": scenario.onset_step,
        "scenario_magnitude_mm": f"{scenario.magnitude * 1e3:g}",
        "scenario_period_steps": scenario.period_steps,
        "physics_dt_ms": f"{model.opt.timestep * 1e3:g}",
        "endoscope_fovy_deg": f"{model.cam_fovy[endoscope]:g}",
        "has_environment_state": _env_state_shape(info) == (18,),
        "has_marks": _env_state_parts(info)[0],
        "has_subtask": _env_state_parts(info)[1],
        "has_relative_actions": _relative_actions(info),
        "has_needle_keypoints": "observation.needle_keypoints" in info["features"],
        "video": info["features"].get("observation.images.endoscope", {}).get("dtype") == "video",
        "grasp": grasp,
        "grasp_blind_expert": bool(log["expert"]["config"].get("assume_nominal_grasp", False)),
        "tissue_damping": f"{tissue.TISSUE_DAMPING:g}",
        "steps_after_success": log.get("steps_after_success", 0),
        "appearance_on": appearance.enabled,
        "appearance_rows": ranges_table(appearance),
        "num_episodes": len(log["episodes"]),
        "num_frames": info["total_frames"],
        "mean_length": sum(lengths) / len(lengths),
        "min_length": min(lengths),
        "max_length": max(lengths),
        "num_discarded": len(log["discarded"]),
        "discard_reasons": ", ".join(f"{n} {r}" for r, n in sorted(reasons.items())),
        "needle_radius_mm": f"{geometry.NEEDLE_RADIUS * 1e3:g}",
        "entry_tolerance_mm": f"{task.ENTRY_TOLERANCE * 1e3:g}",
        "exit_tolerance_mm": f"{task.EXIT_TOLERANCE * 1e3:g}",
        "min_protrusion_mm": f"{task.MIN_PROTRUSION * 1e3:g}",
        "phantom_range_mm": f"{task.PHANTOM_RANGE_XY * 1e3:g}",
        "phantom_yaw_rad": f"{task.PHANTOM_YAW_RANGE:g}",
        "phantom_yaw_deg": f"{math.degrees(task.PHANTOM_YAW_RANGE):.1f}",
        "grasp_angle_deg": f"{math.degrees(grasp_angle):g}",
        "grasp_nominal_deg": f"{math.degrees(task.GRASP_ANGLE):g}",
        "grasp_offset_mm": f"{grasp_offset * 1e3:g}",
        "grasp_roll_rad": f"{grasp_roll:g}",
        "arm_start_noise": ", ".join(f"{x:g}" for x in task.ARM_START_NOISE),
        "expert_class": log["expert"]["class"],
        "expert_config": log["expert"]["config"],
        "n_train": len(train),
        "n_val": len(val),
        "train_range": _index_range(train),
        "val_range": _index_range(val),
        "val_fraction": log["val_fraction"],
        "features": features,
        "command": log["command"],
        "versions": log["versions"],
    }
    env = jinja2.Environment(undefined=jinja2.StrictUndefined, keep_trailing_newline=True)
    return env.from_string(path.read_text()).render(**context)


def card_kwargs(root: str | Path, template_path: str | Path | None = None) -> dict:
    """Keyword arguments for ``LeRobotDataset.push_to_hub`` / ``create_lerobot_dataset_card``."""
    kwargs = {
        "license": LICENSE,
        "dataset_description": render_description(root, template_path),
        "paper": f"[{PAPER_TITLE}]({PAPER_URL})",
        "citation_bibtex": CITATION_BIBTEX,
    }
    if HOMEPAGE:
        kwargs["url"] = HOMEPAGE
    return kwargs


def make_dataset_card(root: str | Path, template_path: str | Path | None = None):
    """The ``huggingface_hub.DatasetCard`` that ``push_to_hub`` uploads for the dataset at ``root``."""
    from lerobot.datasets.io_utils import load_info
    from lerobot.datasets.utils import create_lerobot_dataset_card

    log = metadata.read_episode_log(root)
    return create_lerobot_dataset_card(
        tags=list(TAGS),
        dataset_info=load_info(Path(root)),
        repo_id=log["repo_id"],
        **card_kwargs(root, template_path),
    )


def write_dataset_card(root: str | Path, template_path: str | Path | None = None) -> Path:
    """Write the dataset card to ``root/README.md``; returns its path."""
    path = Path(root) / "README.md"
    make_dataset_card(root, template_path).save(path)
    return path
