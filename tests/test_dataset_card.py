"""The dataset card tells a Hub reader what the data is: synthetic, its sensors, scenario, grasp, limits."""

from __future__ import annotations

import pytest

from lerobot_suture.datasets.card import render_description
from lerobot_suture.datasets.record import record
from lerobot_suture.datasets.record_config import RecordConfig
from lerobot_suture.sim.appearance import AppearanceConfig


@pytest.fixture(scope="module")
def servo_card(tmp_path_factory) -> str:
    """The card of a 2-episode recording of the reference's recipe (moving phantom, grasp-blind expert)."""
    root = tmp_path_factory.mktemp("datasets") / "servo"
    cfg = RecordConfig(
        repo_id="suture-tests/servo",
        root=str(root),
        num_episodes=2,
        image_size=32,
        scenario="phantom_servo",
        steps_after_success=8,
        grasp_blind_expert=True,
        checkpoint_every=2,
    )
    return render_description(record(cfg).root)


def test_card_says_the_data_is_synthetic_and_names_its_sensors(servo_card):
    for needle in (
        "**Synthetic data.**",
        "No frame comes from a real robot",
        "| endoscope camera (`observation.images.endoscope`) |",
        "32x32 px, vertical field of view 42°, MP4 video | 10 Hz |",
        "| state (`observation.state`) |",
        "physics runs at\n2 ms",
    ):
        assert needle in servo_card, needle
    assert "environment state (`observation.environment_state`)" not in servo_card  # not recorded here


def test_card_says_the_scenario_the_grasp_and_the_limitations(servo_card):
    for needle in (
        "Scenario `phantom_servo`: during the approach the phantom glides 8 mm",
        "every\n20 steps",
        "Grasp `narrow`",
        "The expert plans with the nominal grasp",
        "### Known limitations",
        "**Kinematic grasp.**",
        "**Viscous tissue model.**",
        "(2 N per m/s)",
        "**No suture thread.**",
    ):
        assert needle in servo_card, needle
    assert "and the true needle grasp" not in servo_card
    assert "{{" not in servo_card and "{%" not in servo_card


def test_card_says_appearance_is_off_by_default(servo_card):
    assert "### Appearance (per episode, uniform)" in servo_card
    assert "Off: every episode has the scene's own light" in servo_card
    assert "| `haze` | grey veil over the endoscope image | off |" in servo_card


def test_card_lists_the_appearance_ranges_of_a_randomized_recording(tmp_path):
    """One episode recorded with two options on: the card and the recorded command name their ranges."""
    cfg = RecordConfig(
        repo_id="suture-tests/randomized",
        root=str(tmp_path / "randomized"),
        num_episodes=1,
        val_fraction=0.0,
        image_size=32,
        video=False,
        appearance=AppearanceConfig(light_intensity=0.3, camera_position=0.003),
    )
    card = render_description(record(cfg).root)
    assert "randomized once per episode within these ranges" in card
    assert "| `light_intensity` | intensity of every light | x(1 ± 0.3) |" in card
    assert "| `camera_position` | endoscope position along x, y, z | ±3 mm each |" in card
    assert "| `noise` | Gaussian pixel noise per frame, std | off |" in card
    assert "--appearance.light_intensity=0.3 --appearance.camera_position=0.003" in card
