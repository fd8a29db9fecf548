"""Appearance randomization: validated ranges, off by default (bit-identical images), one draw per seed,
each option moves the image the way it says, and none of them touches the physics."""

from __future__ import annotations

import colorsys
import math

import mujoco
import numpy as np
import pytest

from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.sim import appearance
from lerobot_suture.sim.appearance import (
    LIMITS,
    AppearanceConfig,
    AppearanceSample,
    blur_image,
    degrade_image,
    gaussian_kernel,
    haze_image,
    mottled_texture,
)
from lerobot_suture.sim.scene_model import SCENE_XML
from lerobot_suture.sim.suture_env import SutureEnv

SIZE = 48
MODERATE = {name: limit / 3 for name, (limit, _) in LIMITS.items()}


def image(env: SutureEnv, seed: int) -> np.ndarray:
    return env.reset(seed=seed)[0]["pixels"]["endoscope"].astype(np.float64)


def expert_run(env: SutureEnv, seed: int, steps: int = 25):
    expert = ScriptedExpert()
    obs, info = env.reset(seed=seed)
    expert.reset(env)
    run = [(obs, info)]
    for _ in range(steps):
        obs, _, terminated, _, info = env.step(expert.act(env))
        run.append((obs, info))
        if terminated:
            break
    return run


def tissue_mask(clean: np.ndarray) -> np.ndarray:
    """Pixels of the pink tissue pad in an image of the scene's own look."""
    r, g, b = clean[..., 0], clean[..., 1], clean[..., 2]
    return (r > 150) & (r - g > 40) & (r - b > 40)


def spread(pixels: np.ndarray) -> float:
    """Mean difference between the largest and smallest channel: 0 for greys."""
    return float((pixels.max(axis=-1) - pixels.min(axis=-1)).mean())


def mean_hue(pixels: np.ndarray) -> float:
    return colorsys.rgb_to_hsv(*(pixels.mean(axis=0) / 255.0))[0]


# ------------------------------------------------------------------------------------------ config
@pytest.mark.parametrize("name", list(LIMITS))
def test_every_option_is_off_by_default_and_validated_naming_its_range(name):
    assert getattr(AppearanceConfig(), name) == 0.0
    limit, unit = LIMITS[name]
    AppearanceConfig(**{name: limit})  # the ends are allowed
    for bad in (-0.01, limit * 1.01 + 1e-9, math.nan, math.inf):
        with pytest.raises(ValueError, match=rf"`appearance\.{name}` must be in \[0, {limit:g}\] \({unit}\)"):
            AppearanceConfig(**{name: bad})
    with pytest.raises(ValueError, match=rf"`appearance\.{name}` must be a number"):
        AppearanceConfig(**{name: "bright"})


def test_config_from_none_dict_or_config_and_unknown_names_raise():
    assert not AppearanceConfig.from_value(None).enabled
    cfg = AppearanceConfig.from_value({"haze": 0.2})
    assert cfg.enabled and cfg.image_effects and cfg.active() == {"haze": 0.2}
    assert AppearanceConfig.from_value(cfg) is cfg
    assert not AppearanceConfig(camera_roll=0.1).image_effects
    with pytest.raises(ValueError, match=r"Unknown `appearance` option\(s\) \['fog'\]"):
        AppearanceConfig.from_value({"fog": 0.2})
    with pytest.raises(ValueError, match="`appearance` must be an AppearanceConfig"):
        SutureEnv(appearance=0.3)


# ------------------------------------------------------------------------------- pure image effects
def test_image_effects_are_pure_and_do_what_they_say():
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 255, size=(32, 32, 3))
    kept = img.copy()
    taps = gaussian_kernel(1.5)
    assert taps.sum() == pytest.approx(1.0) and len(taps) == 2 * 5 + 1
    blurred = blur_image(img, 1.5)
    np.testing.assert_array_equal(img, kept)  # inputs are not written
    assert np.abs(np.diff(blurred, axis=1)).mean() < 0.5 * np.abs(np.diff(img, axis=1)).mean()
    np.testing.assert_allclose(blur_image(np.full((8, 8, 3), 7.0), 2.0), 7.0)  # a flat image stays flat
    assert blur_image(img, 0.0) is img
    hazed = haze_image(img, 0.5)
    np.testing.assert_allclose(hazed.std(axis=(0, 1)), 0.5 * img.std(axis=(0, 1)))
    np.testing.assert_array_equal(haze_image(img, 0.0), img)
    u8 = img.astype(np.uint8)
    np.testing.assert_array_equal(degrade_image(u8, AppearanceSample(), rng), u8)  # identity look
    noisy = degrade_image(u8, AppearanceSample(noise_std=0.05), np.random.default_rng(1))
    assert noisy.dtype == np.uint8 and 8 < np.std(noisy.astype(float) - u8) < 16  # ~0.05 x 255, clipped
    tex = mottled_texture(3, 0.4)
    assert tex.shape == (appearance.TEXTURE_SIZE,) * 2 + (3,) and tex.dtype == np.uint8
    assert tex.max() == 255 and tex.min() == round(255 * 0.6)
    np.testing.assert_array_equal(tex, mottled_texture(3, 0.4))
    assert mottled_texture(0, 0.0).min() == 255


# --------------------------------------------------------------------------- off, seeds, physics
def test_off_by_default_draws_nothing_and_leaves_the_images_bit_identical():
    """The default env, an all-zero config and an empty dict give the same frames under the expert, those
    frames are the raw renders, and the model keeps the look of scene.xml."""
    envs = [
        SutureEnv(image_size=32),
        SutureEnv(image_size=32, appearance=AppearanceConfig()),
        SutureEnv(image_size=32, appearance={}),
    ]
    runs = [expert_run(env, seed=4, steps=15) for env in envs]
    for run in runs[1:]:
        for (a, _), (b, _) in zip(runs[0], run, strict=True):
            np.testing.assert_array_equal(a["pixels"]["endoscope"], b["pixels"]["endoscope"])
            np.testing.assert_array_equal(a["agent_pos"], b["agent_pos"])
    env = envs[0]
    assert env.appearance_sample is None
    np.testing.assert_array_equal(env.observe()["pixels"]["endoscope"], env._endoscope.image(env.data))
    fresh = mujoco.MjModel.from_xml_path(str(SCENE_XML))
    for field in ("mat_rgba", "geom_rgba", "light_diffuse", "light_ambient", "light_pos", "light_dir"):
        np.testing.assert_array_equal(getattr(env.model, field), getattr(fresh, field), err_msg=field)
    np.testing.assert_array_equal(env.model.vis.headlight.diffuse, fresh.vis.headlight.diffuse)
    assert env.model.ntex == fresh.ntex  # no texture added
    # No generator was spawned: the seed sequence has no children.
    assert env.np_random.bit_generator.seed_seq.n_children_spawned == 0


def test_appearance_changes_the_images_but_never_the_physics():
    off, on = SutureEnv(image_size=32), SutureEnv(image_size=32, appearance=MODERATE)
    run_off, run_on = expert_run(off, seed=2, steps=70), expert_run(on, seed=2, steps=70)
    assert len(run_off) == len(run_on) and run_off[-1][1]["is_success"] and run_on[-1][1]["is_success"]
    for (a, info_a), (b, info_b) in zip(run_off, run_on, strict=True):
        np.testing.assert_array_equal(a["agent_pos"], b["agent_pos"])
        np.testing.assert_array_equal(info_a["needle_tip_pos"], info_b["needle_tip_pos"])
        assert not np.array_equal(a["pixels"]["endoscope"], b["pixels"]["endoscope"])


def test_same_seed_same_look_and_every_reset_starts_from_the_scene_look():
    a, b = SutureEnv(image_size=32, appearance=MODERATE), SutureEnv(image_size=32, appearance=MODERATE)
    for seed in (5, 6):
        np.testing.assert_array_equal(image(a, seed), image(b, seed))
        assert a.appearance_sample == b.appearance_sample
        # The per-frame noise comes from the episode's generator too.
        np.testing.assert_array_equal(a.observe()["pixels"]["endoscope"], b.observe()["pixels"]["endoscope"])
    assert not np.array_equal(image(a, 5), image(a, 6))
    # Episode 6 after episode 5 looks as episode 6 of a fresh env: the last look was undone.
    c = SutureEnv(image_size=32, appearance=MODERATE)
    image(a, 5)
    np.testing.assert_array_equal(image(a, 6), image(c, 6))
    assert a.appearance_sample == c.appearance_sample


# -------------------------------------------------------------------------------- each option
SEEDS = range(6)


def on_off(option: str, value: float, seeds=SEEDS):
    """(sample, image with the option, image without) per seed."""
    on, off = SutureEnv(image_size=SIZE, appearance={option: value}), SutureEnv(image_size=SIZE)
    out = []
    for seed in seeds:
        changed = image(on, seed)
        out.append((on.appearance_sample, changed, image(off, seed)))
    return out


def test_light_intensity_darkens_or_brightens_with_its_draw():
    for sample, lit, clean in on_off("light_intensity", 0.6):
        if abs(sample.light_scale - 1) > 0.1:
            assert np.sign(lit.mean() - clean.mean()) == np.sign(sample.light_scale - 1), sample.light_scale


def test_light_direction_tilts_the_overhead_light_off_the_flat_tissue():
    env = SutureEnv(image_size=SIZE, appearance={"light_direction": 0.8})
    light = env.model.light(appearance.OVERHEAD_LIGHT).id
    env.reset(seed=0)
    direction = env.model.light_dir[light] / np.linalg.norm(env.model.light_dir[light])
    tilt_x, tilt_y = env.appearance_sample.light_tilt
    assert math.cos(tilt_x) * math.cos(tilt_y) == pytest.approx(-direction[2])
    # Still aimed at the work site (the world origin), from as far away.
    np.testing.assert_allclose(np.cross(env.model.light_pos[light], direction), 0.0, atol=1e-12)
    for sample, lit, clean in on_off("light_direction", 0.8):
        if max(abs(t) for t in sample.light_tilt) > 0.2:
            assert lit[tissue_mask(clean)].mean() < clean[tissue_mask(clean)].mean()  # light falls obliquely


def test_tissue_hue_and_value_change_the_tissue_pixels():
    for sample, tinted, clean in on_off("tissue_hue", 0.1):
        mask = tissue_mask(clean)
        shift = (mean_hue(tinted[mask]) - mean_hue(clean[mask]) + 0.5) % 1.0 - 0.5
        if abs(sample.tissue_hue_shift) > 0.02:  # lit and clipped to 255, pixels keep the sign, not the size
            assert np.sign(shift) == np.sign(sample.tissue_hue_shift)
            assert 0.3 < shift / sample.tissue_hue_shift < 3
    for sample, shaded, clean in on_off("tissue_value", 0.5):
        mask = tissue_mask(clean)
        if sample.tissue_value_scale < 0.9:
            assert shaded[mask].mean() < clean[mask].mean() - 5


def test_tissue_texture_mottles_the_pad():
    for sample, textured, clean in on_off("tissue_texture", 1.0):
        mask = tissue_mask(clean)
        if sample.tissue_texture_contrast > 0.5:
            # The texture multiplies the lit colour: the ratio to the clean image varies across the pad.
            ratio = textured[mask].mean(axis=-1) / clean[mask].mean(axis=-1)
            assert ratio.std() > 0.05 and ratio.min() < 0.8 and ratio.max() <= 1.0 + 1e-9


def test_instrument_value_and_tint_change_only_the_instrument():
    for option, value in (("instrument_value", 0.8), ("instrument_tint", 1.0)):
        env = SutureEnv(image_size=SIZE, appearance={option: value})
        env.reset(seed=1)
        fresh = mujoco.MjModel.from_xml_path(str(SCENE_XML))
        changed = np.flatnonzero(np.any(env.model.geom_rgba != fresh.geom_rgba, axis=1))
        assert {env.model.geom(int(g)).name for g in changed} == set(appearance.INSTRUMENT_GEOMS)
        np.testing.assert_array_equal(env.model.mat_rgba, fresh.mat_rgba)
    for sample, tinted, clean in on_off("instrument_tint", 1.0):
        moved = np.any(tinted != clean, axis=-1)
        if sample.instrument_tint > 0.3:
            assert moved.any() and spread(tinted[moved]) > spread(clean[moved])  # greys gain a colour


def test_haze_blur_and_noise_lower_contrast_soften_edges_and_add_variance():
    for sample, hazed, clean in on_off("haze", 0.8):
        assert hazed.std() < clean.std() * (1 - sample.haze) + 1.0
    for sample, blurred, clean in on_off("blur", 0.03):
        if sample.blur_sigma * SIZE > 0.5:
            assert np.abs(np.diff(blurred, axis=1)).mean() < np.abs(np.diff(clean, axis=1)).mean()
    env = SutureEnv(image_size=SIZE, appearance={"noise": 0.1})
    for sample, noisy, clean in on_off("noise", 0.1):
        assert np.std(noisy - clean) == pytest.approx(sample.noise_std * 255, rel=0.3, abs=1.0)
    env.reset(seed=0)
    frames = [env.observe()["pixels"]["endoscope"] for _ in range(2)]
    assert not np.array_equal(*frames)  # new noise every frame
    # render() frames (videos) are clean.
    clean_env = SutureEnv(image_size=SIZE)
    clean_env.reset(seed=0)
    np.testing.assert_array_equal(env.render(), clean_env.render())


def test_camera_roll_turns_the_image_about_its_centre_and_position_jitter_moves_it():
    on, off = SutureEnv(image_size=SIZE, appearance={"camera_roll": 0.5}), SutureEnv(image_size=SIZE)
    for seed in SEEDS:
        on.reset(seed=seed), off.reset(seed=seed)
        roll = on.appearance_sample.camera_roll
        a = off.needle_keypoints_in_image().reshape(3, 2)
        b = on.needle_keypoints_in_image().reshape(3, 2)
        turn = np.arctan2(b[:, 1], b[:, 0]) - np.arctan2(a[:, 1], a[:, 0])
        turn = (turn + np.pi) % (2 * np.pi) - np.pi
        np.testing.assert_allclose(turn, roll, atol=0.02)  # y points down: a +roll turns by +roll here
        np.testing.assert_allclose(np.linalg.norm(b, axis=1), np.linalg.norm(a, axis=1), atol=1e-4)
    on = SutureEnv(image_size=SIZE, appearance={"camera_position": 0.01})
    camera = on.model.camera("endoscope").id
    for seed in SEEDS:
        on.reset(seed=seed), off.reset(seed=seed)
        np.testing.assert_allclose(
            on.model.cam_pos[camera] - off.model.cam_pos[camera], on.appearance_sample.camera_offset
        )
        assert np.abs(on.needle_keypoints_in_image() - off.needle_keypoints_in_image()).max() > 0.01


def test_the_jitter_stays_when_a_scenario_moves_the_endoscope():
    kwargs = {"image_size": SIZE, "scenario": "camera_moved"}
    on, off = SutureEnv(**kwargs, appearance={"camera_roll": 0.5}), SutureEnv(**kwargs)
    on.reset(seed=0), off.reset(seed=0)
    assert on.scenario.perturbed and off.scenario.perturbed
    camera = on.model.camera("endoscope").id
    np.testing.assert_allclose(on.model.cam_pos[camera], off.model.cam_pos[camera])
    assert not np.allclose(on.model.cam_quat[camera], off.model.cam_quat[camera])


# ------------------------------------------------------------------------------------ record flags
def test_record_flags_log_and_resume_check(tmp_path):
    from lerobot_suture.datasets.record_config import parse_config
    from lerobot_suture.datasets.resume import _check_resumable, new_episode_log

    cfg = parse_config(
        ["--repo_id=suture-tests/look", "--appearance.tissue_hue=0.05", "--appearance.haze=0.2"]
    )
    assert cfg.appearance == AppearanceConfig(tissue_hue=0.05, haze=0.2)
    assert cfg.command().endswith("--appearance.tissue_hue=0.05 --appearance.haze=0.2")
    assert parse_config(cfg.command().split()[2:]).appearance == cfg.appearance  # the command re-records it
    log = new_episode_log(cfg)
    assert log["env_kwargs"]["appearance"]["tissue_hue"] == 0.05
    off = parse_config(["--repo_id=suture-tests/look"])
    assert "appearance" not in new_episode_log(off)["env_kwargs"]  # logs without it read as before
    with pytest.raises(ValueError, match=r"`appearance` differs .* --appearance\.tissue_hue=0\.05"):
        _check_resumable(off, log, tmp_path)
    _check_resumable(cfg, log, tmp_path)
    from lerobot_suture.cli import flag_error

    with pytest.raises(Exception) as err:  # the command line shows the config's own message
        parse_config(["--repo_id=suture-tests/look", "--appearance.blur=0.5"])
    assert flag_error(err.value) == (
        "`appearance.blur` must be in [0, 0.05] (fraction of the image side). Got 0.5."
    )


def test_the_randomized_recipe_is_the_servo_recipe_with_moderate_ranges():
    import dataclasses
    from pathlib import Path

    from lerobot_suture.datasets.record_config import parse_config

    recipes = Path(__file__).parents[1] / "recipes"
    servo = parse_config([f"--config_path={recipes / 'suture_expert_servo.yaml'}"])
    randomized = parse_config([f"--config_path={recipes / 'suture_expert_randomized.yaml'}"])
    same = dataclasses.replace(
        randomized, appearance=AppearanceConfig(), repo_id=servo.repo_id, root=servo.root
    )
    assert same == servo
    # Every option on but the endoscope's pose (its jitter cost the policy its precision), none past half
    # its allowed range: larger shifts are left for held-out tests.
    assert set(randomized.appearance.active()) == set(LIMITS) - {"camera_position", "camera_roll"}
    for name, value in randomized.appearance.active().items():
        assert value <= LIMITS[name][0] / 2, name


def test_the_strip_figure_shows_a_frame_per_option(tmp_path):
    """benchmarks/appearance_strip.py (docs/appearance_strip.png) at a small size: written, not blank, and
    every option's column differs from the column with every option off."""
    import importlib.util
    from pathlib import Path

    from PIL import Image

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "appearance_strip.py"
    spec = importlib.util.spec_from_file_location("appearance_strip", path)
    strip = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(strip)
    columns = strip.strip_columns(seed=7, image_size=32, steps=2)
    assert [label.split("\n")[0] for label, _ in columns] == ["off", *LIMITS, "all"]
    off = columns[0][1]
    for label, frame in columns[1:]:
        assert not np.array_equal(frame, off), label
    png = strip.appearance_strip(tmp_path / "strip.png", seed=7, steps=2, columns=columns)
    pixels = np.asarray(Image.open(png).convert("RGB"), dtype=np.float64)
    assert pixels.shape[0] > 200 and pixels.std() > 20
    committed = path.parents[1] / "docs" / "appearance_strip.png"
    assert committed.is_file() and committed.stat().st_size < 200_000
