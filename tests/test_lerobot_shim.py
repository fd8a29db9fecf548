"""The shim (``lerobot_suture/lerobot_shim.py``) checked against the installed LeRobot, and the rule that
nothing else in the product or its plugins reaches LeRobot's private members or rebinds its names.

The version the shim was written for is pinned: on another LeRobot, the first test fails and says what to
check; each other test names the seam that moved.
"""

from __future__ import annotations

import ast
import inspect
import re
import sys
from importlib.metadata import version
from importlib.util import find_spec
from pathlib import Path

import pytest

from lerobot_suture import lerobot_shim

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("lerobot_suture", "envs", "policies", "robots", "teleoperators")
SHIM = ROOT / "lerobot_suture" / "lerobot_shim.py"


def test_lerobot_is_the_version_the_shim_was_written_for():
    installed = version("lerobot")
    assert installed == lerobot_shim.LEROBOT_VERSION, (
        f"LeRobot {installed} is installed; lerobot_suture/lerobot_shim.py was written for LeRobot "
        f"{lerobot_shim.LEROBOT_VERSION}. Check each of its seams against LeRobot {installed} (the other tests "
        "of this file name them: the strategy factory, the episode loops, DAggerStrategy's members, the "
        "ActionQueue's delay, the diffusion model's conditioning, the config writer, the keyboard callbacks), "
        "then set LEROBOT_VERSION there."
    )


def _source(module: str) -> str:
    """A module's source, read without importing it: LeRobot's scripts import its keyboard listener, which
    settles pynput's backend for the whole process (the surgeon's tests pick the headless one first)."""
    root = Path(find_spec("lerobot").origin).parent  # find_spec of a submodule would import its packages
    return (root.joinpath(*module.split(".")[1:]).with_suffix(".py")).read_text()


def test_the_strategy_factory_is_where_the_shim_routes_it():
    from lerobot.rollout.strategies import factory
    from lerobot_robot_suture import rollout_seam

    for name in lerobot_shim.STRATEGY_MODULES:
        if name == "lerobot.scripts.lerobot_rollout":
            assert "create_strategy" in _source(name), f"{name} no longer calls create_strategy"
            continue
        module = __import__(name, fromlist=["create_strategy"])
        assert hasattr(module, "create_strategy"), f"{name} no longer holds create_strategy"
    assert factory.create_strategy.routed["gated_dagger"] is rollout_seam.GatedDAggerStrategy, (
        "the plugin's factory is not installed"
    )


@pytest.mark.parametrize(
    "member",
    ["_events", "_engine", "_interpolator", "_needs_push", "_episode_lock"],
)
def test_dagger_strategy_still_holds_the_members_gated_dagger_uses(member):
    from lerobot.rollout.strategies import core, dagger

    source = inspect.getsource(dagger.DAggerStrategy) + inspect.getsource(core.RolloutStrategy)
    assert f"self.{member} = " in source, (
        f"DAggerStrategy no longer sets self.{member}, which gated_dagger uses"
    )


@pytest.mark.parametrize(
    "method, parameters",
    [
        (
            "_apply_transition",
            ["self", "old_phase", "new_phase", "engine", "interpolator", "ctx", "prev_action"],
        ),
        ("_process_observation_and_notify", ["self", "processors", "obs_raw"]),
    ],
)
def test_dagger_strategy_s_methods_take_what_gated_dagger_passes(method, parameters):
    from lerobot.rollout.strategies.dagger import DAggerStrategy

    assert hasattr(DAggerStrategy, method), f"DAggerStrategy has no {method}, which gated_dagger calls"
    assert list(inspect.signature(getattr(DAggerStrategy, method)).parameters) == parameters


def test_dagger_events_and_the_engines_answer_what_gated_dagger_calls():
    from lerobot.rollout.inference.base import InferenceEngine
    from lerobot.rollout.strategies.dagger import DAggerEvents, DAggerPhase

    events = DAggerEvents()
    assert events.phase is DAggerPhase.AUTONOMOUS and events.consume_transition() is None
    assert hasattr(events, "stop_recording") and callable(events.reset)
    for method in ("start", "stop", "reset", "pause", "resume", "notify_observation", "get_action"):
        assert callable(getattr(InferenceEngine, method, None)), f"InferenceEngine has no {method}"


def test_the_action_queue_still_resolves_its_delay_where_the_shim_overrides_it():
    from lerobot.policies.rtc import ActionQueue
    from lerobot.rollout.inference import rtc

    parameters = list(inspect.signature(ActionQueue._check_and_resolve_delays).parameters)
    assert parameters == ["self", "real_delay", "action_index_before_inference"]
    assert "self._check_and_resolve_delays(real_delay, action_index_before_inference)" in inspect.getsource(
        ActionQueue.merge
    )
    assert "self._action_queue = ActionQueue(" in inspect.getsource(rtc.RTCInferenceEngine.start)


def _calls_with_keywords(module: str, function: str) -> list[set[str]]:
    """The keyword sets of every call of ``function`` (a name or ``self.<name>``) in ``module``'s source."""
    calls = []
    for node in ast.walk(ast.parse(_source(module))):
        if isinstance(node, ast.Call):
            name = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", None)
            if name == function:
                calls.append({k.arg for k in node.keywords})
    return calls


@pytest.mark.parametrize(
    "module, loop",
    [(lerobot_shim.RECORD_SCRIPT, "record_loop"), (lerobot_shim.EPISODIC_STRATEGY, "_policy_loop")],
)
def test_lerobot_runs_an_episode_as_one_call_of_the_loop_the_shim_wraps(module, loop):
    calls = _calls_with_keywords(module, loop)
    assert any({"robot", "dataset"} <= keywords for keywords in calls), (
        f"{module} no longer runs an episode as {loop}(robot=..., dataset=...), which lerobot_shim wraps"
    )


class _Scene:
    """An episode-aware robot that counts what it hears."""

    def __init__(self):
        self.heard = []

    def start_episode(self, episode: int) -> None:
        self.heard.append(("start", episode))

    def end_episode(self) -> None:
        self.heard.append(("end",))


class _Dataset:
    num_episodes = 4


def test_the_wrapped_episodic_loop_tells_an_episode_aware_robot_and_no_other():
    from lerobot.rollout.strategies.episodic import EpisodicStrategy

    lerobot_shim.install_episode_hooks()
    lerobot_shim.install_episode_hooks()  # twice: wrapped once
    wrapped = EpisodicStrategy._policy_loop
    original = wrapped.lerobot_original
    assert not hasattr(original, "lerobot_original")
    calls = []
    EpisodicStrategy._policy_loop = lerobot_shim._with_episodes(
        lambda self, **kwargs: calls.append(kwargs["robot"])
    )
    try:
        scene = _Scene()
        EpisodicStrategy._policy_loop(None, robot=scene, dataset=_Dataset())
        assert scene.heard == [("start", 4), ("end",)] and calls == [scene]
        wrapper = type("ThreadSafeRobot", (), {"inner": scene})()  # lerobot-rollout's wrapper holds `inner`
        EpisodicStrategy._policy_loop(None, robot=wrapper, dataset=_Dataset())
        assert scene.heard[-2:] == [("start", 4), ("end",)]
        EpisodicStrategy._policy_loop(None, robot=object(), dataset=_Dataset())  # not episode-aware
        EpisodicStrategy._policy_loop(None, robot=scene, dataset=None)  # no dataset: not an episode
        assert len(scene.heard) == 4 and len(calls) == 4
    finally:
        EpisodicStrategy._policy_loop = wrapped


@pytest.mark.parametrize(
    "owner, member, parameters",
    [
        (
            "lerobot.policies.diffusion.modeling_diffusion:DiffusionModel",
            "_prepare_global_conditioning",
            ["self", "batch"],
        ),
        ("lerobot.configs.policies:PreTrainedConfig", "_save_pretrained", ["self", "save_directory"]),
        ("lerobot.teleoperators.keyboard.teleop_keyboard:KeyboardTeleop", "_on_press", ["self", "key"]),
        ("lerobot.teleoperators.keyboard.teleop_keyboard:KeyboardTeleop", "_on_release", ["self", "key"]),
    ],
)
def test_the_smaller_reaches_still_take_what_the_shim_passes(owner, member, parameters):
    """Read from the source: importing LeRobot's keyboard teleoperator headless, before the surgeon's tests
    select pynput's dummy backend, would leave it without a keyboard for the whole process."""
    module, _, name = owner.partition(":")
    classes = [
        n for n in ast.walk(ast.parse(_source(module))) if isinstance(n, ast.ClassDef) and n.name == name
    ]
    assert classes, f"{module} no longer defines {name}, which lerobot_shim uses"
    methods = [n for n in classes[0].body if isinstance(n, ast.FunctionDef) and n.name == member]
    assert methods, f"{owner} has no {member}, which lerobot_shim uses"
    assert [a.arg for a in methods[0].args.args] == parameters, (owner, member)


NOT_LEROBOT_S = {"_version": "torch.Tensor._version, the tensor's in-place version counter"}
"""Private names LeRobot defines too, which the product reads on other libraries' objects."""


def _lerobot_private_names() -> set[str]:
    """Private names LeRobot defines: its methods and functions, and attributes it sets on ``self``."""
    root = Path(find_spec("lerobot").origin).parent
    pattern = re.compile(r"(?:\bdef |\bself\.)(_[a-z]\w*)")
    names = {name for path in root.rglob("*.py") for name in pattern.findall(path.read_text())}
    return names - set(NOT_LEROBOT_S)


def _product_sources() -> list[Path]:
    return sorted(p for package in PRODUCT for p in (ROOT / package).rglob("*.py"))


def _defined_names(trees) -> set[str]:
    """Every name the product defines (functions, classes, attributes and variables it assigns, parameters)."""
    names = set()
    for tree in trees.values():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names.add(node.name)
            elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
                names.add(node.attr)
            elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                names.add(node.id)
            elif isinstance(node, ast.arg):
                names.add(node.arg)
    return names


def _lerobot_bindings(tree: ast.AST) -> set[str]:
    """The names a module binds to LeRobot's modules or objects by its imports."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {
                (a.asname or a.name).split(".")[0] for a in node.names if a.name.split(".")[0] == "lerobot"
            }
        elif (
            isinstance(node, ast.ImportFrom)
            and node.level == 0
            and (node.module or "").split(".")[0] == "lerobot"
        ):
            names |= {a.asname or a.name for a in node.names}
    return names


def _reaches(path: Path, tree: ast.AST, private: set[str], bindings: set[str]) -> list[str]:
    found = []
    where = f"{path.relative_to(ROOT)}:"
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr in private:
            found.append(f"{where}{node.lineno} reaches LeRobot's private {node.attr}")
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("lerobot."):
            found += [
                f"{where}{node.lineno} imports LeRobot's private {a.name}"
                for a in node.names
                if a.name.startswith("_")
            ]
        targets = (
            node.targets
            if isinstance(node, ast.Assign)
            else [getattr(node, "target", None)]
            if isinstance(node, (ast.AugAssign, ast.AnnAssign))
            else []
        )
        for target in targets:
            if isinstance(target, ast.Attribute) and (
                target.attr == "__class__"
                or (isinstance(target.value, ast.Name) and target.value.id in bindings)
            ):
                found.append(f"{where}{node.lineno} rebinds {ast.unparse(target)}")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "setattr":
            owner = node.args[0] if node.args else None
            if isinstance(owner, ast.Name) and owner.id in bindings:
                found.append(f"{where}{node.lineno} rebinds {ast.unparse(node)}")
    return found


def test_only_the_shim_reaches_lerobot_s_private_members_or_rebinds_its_names():
    trees = {p: ast.parse(p.read_text(), filename=str(p)) for p in _product_sources()}
    assert SHIM in trees and len(trees) > 100, "the scan misses the product"
    private = _lerobot_private_names() - _defined_names({p: t for p, t in trees.items() if p != SHIM})
    assert {"_events", "_apply_transition", "_prepare_global_conditioning"} <= private
    offenders = [
        reach
        for path, tree in trees.items()
        if path != SHIM
        for reach in _reaches(path, tree, private, _lerobot_bindings(tree))
    ]
    assert not offenders, "only lerobot_suture/lerobot_shim.py may do this:\n" + "\n".join(offenders)
    shim = _reaches(SHIM, trees[SHIM], private, _lerobot_bindings(trees[SHIM]))
    assert any("_events" in r for r in shim) and any("__class__" in r for r in shim), "the scan is blind"


def test_the_scan_sees_a_reach_and_a_rebinding():
    tree = ast.parse(
        "from lerobot.rollout import strategies\nimport lerobot.scripts\n"
        "strategies.create_strategy = f\nsetattr(strategies, 'x', 1)\nq.__class__ = C\nstrategy._events.reset()\n"
    )
    found = _reaches(SHIM, tree, {"_events"}, _lerobot_bindings(tree))
    assert len(found) == 4, found
    assert sys.modules["lerobot_suture.lerobot_shim"] is lerobot_shim
