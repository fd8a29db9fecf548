"""Appearance randomization of the endoscope's view: light, tissue and instrument colour, a tissue texture,
endoscope pose jitter, and haze, blur and noise over the image.

:class:`AppearanceConfig` holds one range per option, each off (0) by default. With any option on, the env
draws an :class:`AppearanceSample` once per episode at ``reset`` (:func:`sample_appearance`), from a child
generator spawned from ``env.np_random``: spawning does not advance the parent's stream, so the phantom,
grasp and arm draws, and therefore the physics, are the same with and without appearance randomization,
and each seed gives the same look. With every option off nothing is drawn and nothing is edited: the
images are bit-identical to an env without the option.

Scene effects are MuJoCo model edits (:class:`SceneAppearance`: light colours and direction, material and
geom colours, the tissue texture) and the endoscope's pose (``Endoscope.set_jitter``); they are undone and
redrawn at every reset. Image effects (:func:`degrade_image`: haze, then lens blur, then sensor noise, in
the order light meets them) are pure numpy functions applied to the endoscope observation only, not to
``render()`` video frames.

=====================  ==========  ==============  ==========================================================
option                 unit        allowed range   per-episode draw (``r`` the option's value)
=====================  ==========  ==============  ==========================================================
``light_intensity``    fraction    [0, 0.9]        every light's colour scaled by ``1 + U(-r, r)``
``light_direction``    rad         [0, 1.0]        the overhead light tilted about world x and y by
                                                   ``U(-r, r)`` each, still aimed at the work site
``tissue_hue``         turn        [0, 0.5]        tissue and wound hue shifted by ``U(-r, r)`` of the
                                                   colour circle
``tissue_value``       fraction    [0, 0.9]        tissue and wound colour scaled by ``1 + U(-r, r)``
``tissue_texture``     fraction    [0, 1]          mottled texture over the tissue pad, a new pattern each
                                                   episode; darkest spot ``1 - U(0, r)`` of the colour
``instrument_value``   fraction    [0, 0.9]        instrument (shaft, wrist, jaws) colour scaled by
                                                   ``1 + U(-r, r)``
``instrument_tint``    fraction    [0, 1]          instrument grey mixed towards a random hue by ``U(0, r)``
``haze``               fraction    [0, 0.9]        image blended with a light grey veil by ``U(0, r)``
``blur``               fraction    [0, 0.05]       Gaussian blur, sigma ``U(0, r)`` of the image side
``noise``              fraction    [0, 0.25]       Gaussian pixel noise, std ``U(0, r)`` of full scale, new
                                                   every frame
``camera_position``    m           [0, 0.02]       endoscope moved by ``U(-r, r)`` along world x, y and z
``camera_roll``        rad         [0, pi]         endoscope rolled about its optical axis by ``U(-r, r)``
=====================  ==========  ==============  ==========================================================

The needle and the entry and exit markers keep their colours: they are what the task is about, and a
change of the needle's look is a perturbation the O.O.D. gate should see (``scenarios``), not a nuisance.
"""

from __future__ import annotations

import colorsys
import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

if TYPE_CHECKING:  # the endoscope is only handed in
    from lerobot_suture.sim.endoscope import Endoscope

LIMITS: dict[str, tuple[float, str]] = {
    "light_intensity": (0.9, "fraction"),
    "light_direction": (1.0, "rad"),
    "tissue_hue": (0.5, "turn"),
    "tissue_value": (0.9, "fraction"),
    "tissue_texture": (1.0, "fraction"),
    "instrument_value": (0.9, "fraction"),
    "instrument_tint": (1.0, "fraction"),
    "haze": (0.9, "fraction"),
    "blur": (0.05, "fraction of the image side"),
    "noise": (0.25, "fraction of full scale"),
    "camera_position": (0.02, "m"),
    "camera_roll": (math.pi, "rad"),
}
"""Largest value of each option and its unit. Scales stay positive, the veil leaves some image."""

TISSUE_MATERIALS = ("tissue", "wound")
INSTRUMENT_GEOMS = ("shaft", "wrist_clevis", "jaw_upper", "jaw_lower")
OVERHEAD_LIGHT = "top"
TISSUE_TEXTURE = "tissue_mottle"
TEXTURE_SIZE = 64  # px per side of the tissue texture
_TEXTURE_GRIDS = (5, 13)  # cells per side of the coarse and fine octaves of the mottling
HAZE_COLOUR = np.array([225.0, 222.0, 218.0])  # a light, slightly warm grey: smoke lit by the endoscope


@dataclass
class AppearanceConfig:
    """Ranges of the per-episode appearance randomization; every option 0 (off) by default.

    Each value is a half-range of a uniform draw about the scene's own look (signed quantities) or the
    largest strength of an effect (haze, blur, noise, texture, tint); see the module docstring's table.

    Args:
        light_intensity: fraction, [0, 0.9]; every light (the endoscope's headlight and the overhead
            light) scaled by ``1 + U(-r, r)``.
        light_direction: rad, [0, 1.0]; tilt of the overhead light about the world x and y axes.
        tissue_hue: turns of the colour circle, [0, 0.5]; hue shift of the tissue pad and wound line.
        tissue_value: fraction, [0, 0.9]; brightness scale ``1 + U(-r, r)`` of the tissue and wound.
        tissue_texture: fraction, [0, 1]; contrast of a mottled texture over the tissue pad.
        instrument_value: fraction, [0, 0.9]; brightness scale of the instrument (shaft, wrist, jaws).
        instrument_tint: fraction, [0, 1]; how far the instrument's grey is mixed towards a random hue.
        haze: fraction, [0, 0.9]; strength of a light grey veil over the endoscope image (smoke, fog).
        blur: fraction of the image side, [0, 0.05]; sigma of a Gaussian blur of the endoscope image.
        noise: fraction of full scale, [0, 0.25]; std of Gaussian pixel noise, redrawn every frame.
        camera_position: m, [0, 0.02]; endoscope position jitter along each world axis.
        camera_roll: rad, [0, pi]; endoscope roll about its optical axis.
    """

    # Light.
    light_intensity: float = 0.0
    light_direction: float = 0.0
    # Tissue.
    tissue_hue: float = 0.0
    tissue_value: float = 0.0
    tissue_texture: float = 0.0
    # Instrument.
    instrument_value: float = 0.0
    instrument_tint: float = 0.0
    # Image.
    haze: float = 0.0
    blur: float = 0.0
    noise: float = 0.0
    # Endoscope pose.
    camera_position: float = 0.0
    camera_roll: float = 0.0

    def __post_init__(self):
        for name, (limit, unit) in LIMITS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ValueError(
                    f"`appearance.{name}` must be a number in [0, {limit:g}] ({unit}). Got {value!r}."
                )
            if not (math.isfinite(value) and 0.0 <= value <= limit):
                raise ValueError(f"`appearance.{name}` must be in [0, {limit:g}] ({unit}). Got {value}.")
            setattr(self, name, float(value))

    @property
    def enabled(self) -> bool:
        """Any option is on."""
        return any(getattr(self, name) > 0 for name in LIMITS)

    @property
    def image_effects(self) -> bool:
        """Haze, blur or noise is on: the endoscope image is post-processed."""
        return self.haze > 0 or self.blur > 0 or self.noise > 0

    def active(self) -> dict[str, float]:
        """The options that are on, by name."""
        return {name: getattr(self, name) for name in LIMITS if getattr(self, name) > 0}

    @classmethod
    def from_value(cls, value: AppearanceConfig | dict | None) -> AppearanceConfig:
        """``value`` as a config: None is all off, a dict names some fields (an unknown name raises)."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            unknown = sorted(set(value) - set(LIMITS))
            if unknown:
                raise ValueError(f"Unknown `appearance` option(s) {unknown}; the options are {list(LIMITS)}.")
            return cls(**value)
        raise ValueError(
            f"`appearance` must be an AppearanceConfig, a dict of its fields, or None. Got {type(value).__name__}."
        )


@dataclass(frozen=True)
class AppearanceSample:
    """One episode's draw of :class:`AppearanceConfig` (the identity look where an option is off)."""

    light_scale: float = 1.0
    light_tilt: tuple[float, float] = (0.0, 0.0)  # rad about world x, then y
    tissue_hue_shift: float = 0.0  # turns
    tissue_value_scale: float = 1.0
    tissue_texture_contrast: float = 0.0
    tissue_texture_seed: int = 0
    instrument_value_scale: float = 1.0
    instrument_tint_hue: float = 0.0  # turns
    instrument_tint: float = 0.0
    haze: float = 0.0
    blur_sigma: float = 0.0  # fraction of the image side
    noise_std: float = 0.0  # fraction of full scale
    camera_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, world
    camera_roll: float = 0.0  # rad

    @property
    def image_effects(self) -> bool:
        """Haze, blur or noise is on: the endoscope image is post-processed."""
        return self.haze > 0 or self.blur_sigma > 0 or self.noise_std > 0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def sample_appearance(config: AppearanceConfig, rng: np.random.Generator) -> AppearanceSample:
    """Draw one episode's look. Every quantity is drawn, in a fixed order, whether its option is on or
    not, so that turning one option on does not change the draws of the others."""

    def signed(r: float, size: int | None = None):
        return rng.uniform(-1.0, 1.0, size=size) * r

    light_scale = 1.0 + signed(config.light_intensity)
    tilt = signed(config.light_direction, 2)
    hue_shift = signed(config.tissue_hue)
    tissue_scale = 1.0 + signed(config.tissue_value)
    contrast = rng.uniform() * config.tissue_texture
    texture_seed = int(rng.integers(2**31))
    instrument_scale = 1.0 + signed(config.instrument_value)
    tint_hue = rng.uniform()
    tint = rng.uniform() * config.instrument_tint
    haze = rng.uniform() * config.haze
    blur = rng.uniform() * config.blur
    noise = rng.uniform() * config.noise
    offset = signed(config.camera_position, 3)
    roll = signed(config.camera_roll)
    return AppearanceSample(
        light_scale=float(light_scale),
        light_tilt=(float(tilt[0]), float(tilt[1])),
        tissue_hue_shift=float(hue_shift),
        tissue_value_scale=float(tissue_scale),
        tissue_texture_contrast=float(contrast),
        tissue_texture_seed=texture_seed,
        instrument_value_scale=float(instrument_scale),
        instrument_tint_hue=float(tint_hue),
        instrument_tint=float(tint),
        haze=float(haze),
        blur_sigma=float(blur),
        noise_std=float(noise),
        camera_offset=(float(offset[0]), float(offset[1]), float(offset[2])),
        camera_roll=float(roll),
    )


# ----------------------------------------------------------------------------------------- colours
def shift_hue(rgb: np.ndarray, shift: float, value_scale: float = 1.0) -> np.ndarray:
    """``rgb`` (3,) in [0, 1] with its hue turned by ``shift`` turns and its value scaled, clipped to [0, 1]."""
    if shift == 0 and value_scale == 1:
        return np.asarray(rgb, dtype=np.float64).copy()  # exactly: the HSV round trip is off by an ulp
    h, s, v = colorsys.rgb_to_hsv(*np.clip(rgb, 0.0, 1.0))
    return np.clip(colorsys.hsv_to_rgb((h + shift) % 1.0, s, v * value_scale), 0.0, 1.0)


def tint_grey(rgb: np.ndarray, hue: float, amount: float, value_scale: float = 1.0) -> np.ndarray:
    """``rgb`` (3,) mixed by ``amount`` towards the saturated colour of ``hue`` at the same value, then
    scaled by ``value_scale``; clipped to [0, 1]."""
    rgb = np.clip(rgb, 0.0, 1.0)
    target = np.array(colorsys.hsv_to_rgb(hue % 1.0, 1.0, float(rgb.max())))
    return np.clip(((1.0 - amount) * rgb + amount * target) * value_scale, 0.0, 1.0)


def mottled_texture(seed: int, contrast: float, size: int = TEXTURE_SIZE) -> np.ndarray:
    """A smooth random mottling, (size, size, 3) uint8 white-to-grey, to multiply a material's colour.

    Two octaves of bilinearly upsampled uniform noise; the darkest spot is ``1 - contrast`` of white.
    """
    rng = np.random.default_rng(seed)
    field = np.zeros((size, size))
    for cells, weight in zip(_TEXTURE_GRIDS, (0.65, 0.35), strict=True):
        grid = rng.uniform(size=(cells + 1, cells + 1))
        coords = np.linspace(0.0, cells, size)
        i = np.minimum(coords.astype(int), cells - 1)
        f = coords - i
        rows = grid[i] * (1 - f)[:, None] + grid[i + 1] * f[:, None]  # (size, cells + 1)
        field += weight * (rows[:, i] * (1 - f) + rows[:, i + 1] * f)
    span = field.max() - field.min()
    field = (field - field.min()) / (span if span > 0 else 1.0)  # [0, 1]
    value = 255.0 * (1.0 - contrast * field)
    return np.repeat(np.rint(value).astype(np.uint8)[:, :, None], 3, axis=2)


def add_tissue_texture(spec: mujoco.MjSpec) -> None:
    """Give the tissue material a (white) texture whose pixels each episode rewrites: only for an env
    with ``tissue_texture`` on, so that the default scene stays the one in ``scene.xml``."""
    texture = spec.add_texture(
        name=TISSUE_TEXTURE,
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        width=TEXTURE_SIZE,
        height=TEXTURE_SIZE,
        nchannel=3,
    )
    texture.data = bytes(np.full(TEXTURE_SIZE * TEXTURE_SIZE * 3, 255, dtype=np.uint8))
    spec.material("tissue").textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = TISSUE_TEXTURE


# ------------------------------------------------------------------------------------ image effects
def haze_image(image: np.ndarray, amount: float, colour: np.ndarray = HAZE_COLOUR) -> np.ndarray:
    """(H, W, 3) float image blended with a uniform veil: ``(1 - amount) * image + amount * colour``."""
    return (1.0 - amount) * image + amount * colour


def gaussian_kernel(sigma_px: float) -> np.ndarray:
    """Normalized 1-D Gaussian taps, radius ``ceil(3 sigma)`` (at least 1)."""
    radius = max(1, math.ceil(3.0 * sigma_px))
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    taps = np.exp(-0.5 * (x / max(sigma_px, 1e-6)) ** 2)
    return taps / taps.sum()


def blur_image(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """(H, W, C) float image blurred by a separable Gaussian of ``sigma_px`` pixels (edges reflected)."""
    if sigma_px <= 0:
        return image
    taps = gaussian_kernel(sigma_px)
    r = len(taps) // 2
    out = image
    for axis in (0, 1):
        moved = np.moveaxis(out, axis, 0)  # filter along the first axis: slices are views, not copies
        n = moved.shape[0]
        padded = np.pad(moved, [(r, r)] + [(0, 0)] * (moved.ndim - 1), mode="reflect" if n > r else "edge")
        acc = taps[0] * padded[:n]
        for k in range(1, len(taps)):
            acc += taps[k] * padded[k : k + n]
        out = np.moveaxis(acc, 0, axis)
    return out


def noisy_image(image: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W, C) float image (0-255) plus Gaussian noise of ``std`` x 255 per pixel and channel."""
    if std <= 0:
        return image
    return image + rng.normal(0.0, std * 255.0, size=image.shape)


def degrade_image(image: np.ndarray, sample: AppearanceSample, rng: np.random.Generator) -> np.ndarray:
    """The endoscope image (H, W, 3) uint8 through haze, lens blur and sensor noise; uint8 out.

    ``rng`` draws the noise (the episode's generator, so a seed gives the same frames).
    """
    out = image.astype(np.float64)
    if sample.haze > 0:
        out = haze_image(out, sample.haze)
    out = blur_image(out, sample.blur_sigma * image.shape[0])
    out = noisy_image(out, sample.noise_std, rng)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------- scene edits
def _rotation_xy(tilt_x: float, tilt_y: float) -> np.ndarray:
    cx, sx, cy, sy = math.cos(tilt_x), math.sin(tilt_x), math.cos(tilt_y), math.sin(tilt_y)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    return ry @ rx


class SceneAppearance:
    """The model fields an :class:`AppearanceSample` edits, looked up by name once, with their values in
    ``scene.xml`` so that every episode starts from the scene's own look.

    Args:
        model: the scene's MuJoCo model (edited in place by :meth:`apply`).
    """

    def __init__(self, model: mujoco.MjModel):
        self._model = model
        self._light = model.light(OVERHEAD_LIGHT).id
        self._materials = [model.material(name).id for name in TISSUE_MATERIALS]
        self._instrument = [model.geom(name).id for name in INSTRUMENT_GEOMS]
        self._texture = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, TISSUE_TEXTURE)
        head = model.vis.headlight
        self._default = {
            "head": (head.ambient.copy(), head.diffuse.copy(), head.specular.copy()),
            "light": tuple(
                getattr(model, f)[self._light].copy()
                for f in ("light_ambient", "light_diffuse", "light_specular", "light_pos", "light_dir")
            ),
            "mat_rgba": model.mat_rgba[self._materials].copy(),
            "geom_rgba": model.geom_rgba[self._instrument].copy(),
        }

    @property
    def texture_id(self) -> int | None:
        """The tissue texture's id, None when the model has none (``tissue_texture`` off)."""
        return self._texture if self._texture >= 0 else None

    def apply(self, sample: AppearanceSample) -> bool:
        """Set the scene's look to ``sample`` (from the defaults, so the last episode's is undone).

        Returns:
            True when the tissue texture's pixels were rewritten (renderers must upload it again).
        """
        m, d = self._model, self._default
        s = sample.light_scale
        head = m.vis.headlight
        head.ambient[:], head.diffuse[:], head.specular[:] = (x * s for x in d["head"])
        ambient, diffuse, specular, pos, direction = d["light"]
        rotation = _rotation_xy(*sample.light_tilt)
        m.light_ambient[self._light] = ambient * s
        m.light_diffuse[self._light] = diffuse * s
        m.light_specular[self._light] = specular * s
        # Tilted about the world origin (the work site), so the light still shines on it.
        m.light_pos[self._light] = rotation @ pos
        m.light_dir[self._light] = rotation @ direction
        for k, mat in enumerate(self._materials):
            rgba = d["mat_rgba"][k]
            m.mat_rgba[mat, :3] = shift_hue(rgba[:3], sample.tissue_hue_shift, sample.tissue_value_scale)
        for k, geom in enumerate(self._instrument):
            rgba = d["geom_rgba"][k]
            m.geom_rgba[geom, :3] = tint_grey(
                rgba[:3], sample.instrument_tint_hue, sample.instrument_tint, sample.instrument_value_scale
            )
        if self.texture_id is None:
            return False
        adr, n = m.tex_adr[self._texture], TEXTURE_SIZE * TEXTURE_SIZE * 3
        m.tex_data[adr : adr + n] = mottled_texture(
            sample.tissue_texture_seed, sample.tissue_texture_contrast
        ).ravel()
        return True

    def restore(self) -> bool:
        """The scene's own look (``scene.xml``). Returns whether the texture changed (see :meth:`apply`)."""
        return self.apply(AppearanceSample())


class EpisodeAppearance:
    """This episode's look: drawn from the env's ranges at every reset, shown in the scene and through the
    endoscope, and laid over the endoscope's images.

    Args:
        config: the env's appearance ranges.
        scene: the model fields a sample edits.
        endoscope: the camera (its pose jitter, and its renderers' copy of the tissue texture).
        other_cameras: cameras that see the scene too (the wrist camera), their texture kept up to date.

    Attributes:
        sample: the look in force; None while every option is off and no look was set by hand.
    """

    def __init__(
        self, config: AppearanceConfig, scene: SceneAppearance, endoscope: Endoscope, other_cameras=()
    ):
        self.config, self._scene, self._endoscope = config, scene, endoscope
        self._cameras = (endoscope, *other_cameras)
        self.sample: AppearanceSample | None = None
        self._rng: np.random.Generator | None = None

    def draw(self, np_random: np.random.Generator) -> None:
        """This episode's look, from a generator spawned from the env's ``np_random``; nothing is drawn or
        edited when every option is off, but a look set by :meth:`set` in the last episode is undone."""
        if not self.config.enabled:
            if self.sample is not None:
                self._show(AppearanceSample(), None)
                self.sample = None
            return
        rng = child_generator(np_random)
        self._show(sample_appearance(self.config, rng), rng)

    def set(self, sample: AppearanceSample, np_random: np.random.Generator) -> None:
        """Show ``sample`` in place of the drawn look, the endoscope kept at its current viewpoint."""
        self._show(sample, child_generator(np_random))
        self._endoscope.set_viewpoint(*self._endoscope.viewpoint)

    def degrade(self, image: np.ndarray) -> np.ndarray:
        """The endoscope observation ``image`` under the look's haze, blur and noise (unchanged without)."""
        if self.sample is not None and self.sample.image_effects:
            return degrade_image(image, self.sample, self._rng)
        return image

    def _show(self, sample: AppearanceSample, rng: np.random.Generator | None) -> None:
        self.sample, self._rng = sample, rng
        if self._scene.apply(sample):
            for camera in self._cameras:
                camera.upload_texture(self._scene.texture_id)
        self._endoscope.set_jitter(sample.camera_offset, sample.camera_roll)


def child_generator(np_random: np.random.Generator) -> np.random.Generator:
    """A generator spawned from ``np_random``, whose stream it leaves where it was: the task draws that
    follow are those of the same seed without appearance randomization."""
    try:
        return np_random.spawn(1)[0]
    except (TypeError, ValueError):  # a generator set by hand without a seed sequence
        return np.random.default_rng(np_random.integers(2**63))


def ranges_table(config: AppearanceConfig) -> list[dict[str, str]]:
    """One row per option for the dataset card: ``option``, ``what`` it varies and its ``range`` in words
    (``off`` when 0)."""
    c = config
    pct = "{:.0%}".format
    rows = [
        ("light_intensity", "intensity of every light", f"x(1 ± {c.light_intensity:g})"),
        ("light_direction", "overhead light's tilt about x and y", f"±{c.light_direction:g} rad each"),
        ("tissue_hue", "hue of the tissue and wound", f"±{c.tissue_hue:g} turn"),
        ("tissue_value", "brightness of the tissue and wound", f"x(1 ± {c.tissue_value:g})"),
        (
            "tissue_texture",
            "mottled texture on the tissue (darkest spot)",
            f"0 to {pct(c.tissue_texture)} darker",
        ),
        ("instrument_value", "brightness of the instrument", f"x(1 ± {c.instrument_value:g})"),
        ("instrument_tint", "instrument grey mixed towards a random hue", f"0 to {pct(c.instrument_tint)}"),
        ("haze", "grey veil over the endoscope image", f"0 to {pct(c.haze)}"),
        ("blur", "Gaussian blur of the image, sigma", f"0 to {c.blur:g} of the image side"),
        ("noise", "Gaussian pixel noise per frame, std", f"0 to {c.noise:g} of full scale"),
        ("camera_position", "endoscope position along x, y, z", f"±{c.camera_position * 1e3:g} mm each"),
        ("camera_roll", "endoscope roll about its optical axis", f"±{c.camera_roll:g} rad"),
    ]
    return [
        {"option": name, "what": what, "range": text if getattr(c, name) > 0 else "off"}
        for name, what, text in rows
    ]
