"""The task family: each task's instruction, gym id, episode length and the scenarios that apply to it.

``SutureEnv(task=...)`` simulates one of them; LeRobot's ``--env.task=`` names one. ``insertion`` is the
default and the paper's task; its numbers live in ``task``.
"""

from __future__ import annotations

from dataclasses import dataclass

from lerobot_suture.sim import task as insertion
from lerobot_suture.sim.scenarios import SAFETY_SCENARIOS, SCENARIOS


@dataclass(frozen=True)
class TaskSpec:
    """One task of the family.

    Attributes:
        name: the value of ``task=``.
        instruction: the task string of the dataset's frames and of policy inputs.
        gym_id: its Gymnasium id (registered with ``max_episode_steps``).
        max_episode_steps: control steps before truncation (10 Hz).
        throws: how many throws (needle passes through tissue) an episode holds: the CBF guards each.
        scenarios: the perturbation scenarios that make sense for it (``scenarios.SCENARIOS``).
        scenario_onsets: (scenario, onset step) pairs where the task's default onset differs from the
            scenario's own.
    """

    name: str
    instruction: str
    gym_id: str
    max_episode_steps: int
    throws: int
    scenarios: tuple[str, ...]
    scenario_onsets: tuple[tuple[str, int], ...] = ()

    def default_onset(self, scenario: str) -> int | None:
        """The onset step a scenario takes in this task by default (None: the scenario's own default)."""
        return dict(self.scenario_onsets).get(scenario)


TASKS: dict[str, TaskSpec] = {
    spec.name: spec
    for spec in (
        TaskSpec(
            name="insertion",
            instruction=insertion.TASK,
            gym_id="lerobot_suture/NeedleInsertion-v0",
            max_episode_steps=100,
            throws=1,
            scenarios=SCENARIOS,
        ),
        TaskSpec(
            name="pickup",
            instruction="Pick up the suture needle from the phantom, grasped near its tail, ready for a throw.",
            gym_id="lerobot_suture/NeedlePickup-v0",
            max_episode_steps=120,
            throws=0,
            scenarios=("nominal", "needle_drop", "camera_moved", "phantom_servo"),
            # Lost 2 steps after the jaw catches it: while it is being lifted.
            scenario_onsets=(("needle_drop", 2),),
        ),
        TaskSpec(
            name="extraction",
            instruction="Release the needle, regrasp it near its tip and pull it out of the tissue along its arc.",
            gym_id="lerobot_suture/NeedleExtraction-v0",
            max_episode_steps=150,
            throws=0,
            scenarios=("nominal", "needle_drop", "camera_moved", "phantom_moved_after_insertion"),
            # The jaw lets go of the tail first: lose the regrasped needle midway through the pull.
            scenario_onsets=(("needle_drop", 70),),
        ),
        TaskSpec(
            name="running_suture",
            instruction=(
                "Run a suture of four throws along the wound: insert the needle at each entry point and out of "
                "its exit point, extract it and regrasp it, then go on to the next pair."
            ),
            gym_id="lerobot_suture/RunningSuture-v0",
            max_episode_steps=1000,
            throws=4,
            scenarios=SCENARIOS,
        ),
    )
}
TASK_NAMES = tuple(TASKS)
DEFAULT_TASK = "insertion"


def task_spec(name: str) -> TaskSpec:
    """The spec of task ``name``; a ValueError lists the tasks otherwise."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"`task` must be one of {list(TASKS)}. Got {name!r}.") from None


def check_scenario(task_name: str, scenario: str) -> None:
    """Raise a ValueError unless ``scenario`` applies to the task (a perturbation of a phase it lacks); the
    safety benchmarks' tissue motions (``SAFETY_SCENARIOS``) apply to every task with a throw."""
    spec = task_spec(task_name)
    allowed = list(spec.scenarios) + (list(SAFETY_SCENARIOS) if spec.throws > 0 else [])
    if scenario not in allowed:
        raise ValueError(
            f"scenario {scenario!r} does not apply to task {task_name!r}; its scenarios are {allowed}."
        )
