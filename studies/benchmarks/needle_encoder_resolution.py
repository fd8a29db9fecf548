#!/usr/bin/env python
"""Can the members' image encoder find the needle, and does the resolution of its last feature map decide it?

LeRobot's diffusion image encoder (ResNet-18 to its last block, then a spatial softmax) turns the CPU preset's
72 px image into a 3 x 3 feature map. This benchmark trains that encoder, and the same one cut after an earlier
block (a finer map), for a few hundred steps on one task only: regress the needle's tip, middle and tail in the
image (`observation.needle_keypoints`) from the endoscope image. The frames come from the grasp-blind expert
(`record --grasp_blind_expert=true`), so the needle's place is not implied by the jaw and the phantom. Then on
held-out episodes it reports, per encoder, one JSON line:

- ``feature_map``: the side of the map the spatial softmax reads;
- ``keypoint_error_px``: the mean distance of the estimated points from the true ones (pixels at 96 px);
- ``hidden_keypoint_shift_px``: how far the estimate moves when the needle is hidden (`observe(needle_visible=
  False)`). Near 0: the encoder infers the needle from the jaw, it does not see it;
- ``jaw_only_error_px``: the error of the best estimate that does not look at the needle (the nominal grasp's
  keypoints under the true jaw pose), the bar to beat.

    python studies/benchmarks/needle_encoder_resolution.py [--episodes 30] [--steps 400]

Seeds 4,000,000 on (disjoint from every other use). On 2 cores, 20 episodes and 1,500 steps took 9 minutes.
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import lerobot_suture  # noqa: E402
from lerobot_suture.expert import ExpertConfig, ScriptedExpert  # noqa: E402
from lerobot_suture.sim import task  # noqa: E402

SEED_BASE = 4_000_000
IMAGE_SIZE = 96
RESIZE = 72


def collect(episodes: int) -> dict[str, np.ndarray]:
    """Per frame of the grasp-blind expert's nominal episodes: the image shown and with the needle hidden, the
    true keypoints, the keypoints of the nominal grasp under the same jaw pose, and the episode index."""
    env = gym.make(
        lerobot_suture.ENV_ID, obs_type="pixels_agent_pos", image_size=IMAGE_SIZE, disable_env_checker=True
    )
    sim = env.unwrapped
    rows = {"shown": [], "hidden": [], "keypoints": [], "jaw_only": [], "episode": []}
    for k in range(episodes):
        obs, _ = env.reset(seed=SEED_BASE + k)
        expert = ScriptedExpert(ExpertConfig(assume_nominal_grasp=True))
        expert.reset(env)
        done = False
        while not done:
            rows["shown"].append(obs["pixels"]["endoscope"])
            rows["hidden"].append(sim.observe(needle_visible=False)["pixels"]["endoscope"])
            rows["keypoints"].append(sim.needle_keypoints_in_image())
            true_grasp = sim.grasp_parameters
            sim.set_grasp(task.GRASP_ANGLE, 0.0, 0.0)  # where the jaw alone says the needle is
            rows["jaw_only"].append(sim.needle_keypoints_in_image())
            sim.set_grasp(*true_grasp)
            rows["episode"].append(k)
            obs, _, terminated, truncated, _ = env.step(expert.act(env))
            done = terminated or truncated
    env.close()
    return {key: np.stack(value) for key, value in rows.items()}


def make_encoder(blocks: int) -> tuple[torch.nn.Module, int]:
    """LeRobot's diffusion image encoder (GroupNorm ResNet-18, spatial softmax, 32 keypoints) with the backbone
    cut after ResNet block ``blocks`` (4: LeRobot's own); a linear head to the 6 keypoint coordinates."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionRgbEncoder
    from lerobot_policy_ensemble_diffusion.members import cut_image_backbone

    config = DiffusionConfig(
        input_features={
            "observation.images.endoscope": PolicyFeature(
                type=FeatureType.VISUAL, shape=(3, IMAGE_SIZE, IMAGE_SIZE)
            ),
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(10,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(10,))},
        pretrained_backbone_weights=None,
        use_group_norm=True,
        resize_shape=(RESIZE, RESIZE),
        crop_shape=None,
        spatial_softmax_num_keypoints=32,
    )
    encoder = DiffusionRgbEncoder(config)
    if blocks < 4:
        cut_image_backbone(encoder, blocks, (1, 3, RESIZE, RESIZE), num_keypoints=32)
    with torch.no_grad():
        side = encoder.backbone(torch.zeros(1, 3, RESIZE, RESIZE)).shape[-1]
    model = torch.nn.Sequential(encoder, torch.nn.Linear(encoder.feature_dim, 6))
    return model, side


def to_tensor(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0


def run(blocks: int, data: dict, train: np.ndarray, test: np.ndarray, steps: int, seed: int) -> dict:
    torch.manual_seed(seed)
    model, side = make_encoder(blocks)
    optimizer = torch.optim.AdamW(model.parameters(), lr=3e-4, weight_decay=1e-4)
    images, targets = to_tensor(data["shown"][train]), torch.from_numpy(data["keypoints"][train])
    generator = torch.Generator().manual_seed(seed)
    started = time.perf_counter()
    model.train()
    for _ in range(steps):
        index = torch.randint(0, len(images), (32,), generator=generator)
        loss = torch.nn.functional.mse_loss(model(images[index]), targets[index])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    model.eval()
    px = IMAGE_SIZE / 2
    with torch.no_grad():
        shown = model(to_tensor(data["shown"][test])).numpy().reshape(-1, 3, 2)
        hidden = model(to_tensor(data["hidden"][test])).numpy().reshape(-1, 3, 2)
    truth = data["keypoints"][test].reshape(-1, 3, 2)
    jaw_only = data["jaw_only"][test].reshape(-1, 3, 2)
    return {
        "backbone_blocks": blocks,
        "feature_map": side,
        "keypoint_error_px": round(float(px * np.linalg.norm(shown - truth, axis=2).mean()), 3),
        "hidden_keypoint_shift_px": round(float(px * np.linalg.norm(hidden - shown, axis=2).mean()), 3),
        "jaw_only_error_px": round(float(px * np.linalg.norm(jaw_only - truth, axis=2).mean()), 3),
        "train_frames": int(train.sum()),
        "test_frames": int(test.sum()),
        "steps": steps,
        "seconds": round(time.perf_counter() - started, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--blocks", default="4,3,2", help="ResNet blocks kept, one encoder each")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    data = collect(args.episodes)
    test = data["episode"] >= int(0.8 * args.episodes)
    for blocks in (int(b) for b in args.blocks.split(",")):
        result = run(blocks, data, ~test, test, args.steps, seed=blocks)
        print(json.dumps({"benchmark": "needle_encoder_resolution", **result}), flush=True)


if __name__ == "__main__":
    main()
