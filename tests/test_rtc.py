"""Real-time chunking in ``ensemble_diffusion``: the committed prefix is inpainted exactly, in either sampler and
for either prediction type; LeRobot's RTC engine accepts the policy; an enforced gate's flagged chunk holds."""

import numpy as np
import pytest
import torch
from lerobot.rollout.inference.rtc import supports_rtc_inference
from lerobot_policy_ensemble_diffusion.modeling_ensemble_diffusion import EnsembleDiffusionPolicy
from lerobot_policy_ensemble_diffusion.rtc_inpainting import committed_prefix
from policy_builders import fake_dataset_stats, random_observation, tiny_config

from lerobot_suture.safety.ood.calibration import fit_calibration


def make_policy(**overrides) -> EnsembleDiffusionPolicy:
    torch.manual_seed(0)
    config = tiny_config(n_obs_steps=1, noise_scheduler_type="DDIM", num_inference_steps=4, **overrides)
    return EnsembleDiffusionPolicy(config, dataset_stats=fake_dataset_stats()).eval()


def padded_left_over(rows: int, pad_to: int = 10, seed: int = 1) -> torch.Tensor:
    """What the engine hands over: ``rows`` normalized actions, zero-padded to its execution horizon."""
    g = torch.Generator().manual_seed(seed)
    out = torch.zeros(pad_to, 10)
    out[:rows] = torch.rand(rows, 10, generator=g) * 1.6 - 0.8
    return out


def test_the_policy_declares_rtc_as_lerobot_s_engine_checks_it():
    assert supports_rtc_inference(make_policy())


@pytest.mark.parametrize("batched", [True, False])
@pytest.mark.parametrize("prediction_type", ["sample", "epsilon"])
def test_the_committed_prefix_is_the_chunk_s_start_in_every_sample(batched, prediction_type):
    policy = make_policy(batched_inference=batched, prediction_type=prediction_type, n_members=2)
    left_over = padded_left_over(rows=5)
    chunk = policy.predict_action_chunk(
        random_observation(policy.config, n_steps=0), inference_delay=3, prev_chunk_left_over=left_over
    )
    assert chunk.shape == (1, policy.config.horizon, 10)
    torch.testing.assert_close(chunk[0, :3], left_over[:3], atol=1e-5, rtol=0)
    samples = policy.last_prediction.normalized.samples  # (B, N, K, T, A)
    torch.testing.assert_close(
        samples[0, :, :, :3], left_over[:3].expand_as(samples[0, :, :, :3]), atol=1e-5, rtol=0
    )
    # The new part is sampled, not copied: it differs from what was left of the previous chunk.
    assert not torch.allclose(chunk[0, 3:5], left_over[3:5], atol=1e-2)
    # The score is read over the executed steps after the prefix.
    assert policy.last_prediction.action_steps == slice(3, 3 + policy.config.n_action_steps)


def test_a_free_score_is_the_sync_score_of_the_observation_and_leaves_the_chunk_as_it_was():
    """``rtc_score="free"``: the gate reads a second prediction without the prefix, the one the sync engine
    scores, while the executed chunk is the same inpainted one."""
    inpainted, free = make_policy(n_members=3), make_policy(n_members=3, rtc_score="free")
    k, horizon = inpainted.config.uncertainty_samples_per_member, inpainted.config.horizon
    noise = torch.randn(1, 3, k, horizon, 10, generator=torch.Generator().manual_seed(2))
    observation, left_over = random_observation(inpainted.config, n_steps=0), padded_left_over(rows=5)
    chunks = [
        policy.predict_action_chunk(
            observation, noise=noise, inference_delay=3, prev_chunk_left_over=left_over
        )
        for policy in (inpainted, free)
    ]
    torch.testing.assert_close(chunks[0], chunks[1])
    stacked = random_observation(inpainted.config)  # the same observation, as (B, n_obs_steps, ...)
    sync = make_policy(n_members=3).predict_action_distribution(stacked, noise=noise)
    torch.testing.assert_close(free.last_prediction.score, sync.score)
    assert not torch.allclose(inpainted.last_prediction.score, sync.score)
    assert free.last_prediction.action_steps == slice(
        3, 3 + free.config.n_action_steps
    )  # the executed chunk's
    with pytest.raises(ValueError, match="rtc_score"):
        make_policy(rtc_score="guided")


def test_no_prefix_on_the_first_chunk_and_the_score_over_the_usual_steps():
    policy = make_policy()
    chunk = policy.predict_action_chunk(
        random_observation(policy.config, n_steps=0), inference_delay=0, prev_chunk_left_over=None
    )
    assert chunk.shape == (1, policy.config.horizon, 10)
    assert policy.last_prediction.action_steps == slice(0, policy.config.n_action_steps)


def test_a_delay_longer_than_the_chunk_commits_the_whole_chunk():
    """Inference slower than the chunk is long: every step of the new chunk is already committed."""
    policy = make_policy()
    left_over = padded_left_over(rows=10, pad_to=10)
    chunk = policy.predict_action_chunk(
        random_observation(policy.config, n_steps=0), inference_delay=12, prev_chunk_left_over=left_over
    )
    torch.testing.assert_close(chunk[0], left_over[: policy.config.horizon], atol=1e-5, rtol=0)


def test_the_prefix_stops_at_the_engine_s_padding_and_at_the_delay():
    left_over = padded_left_over(rows=2)
    assert committed_prefix(left_over, 4).shape == (2, 10)
    assert committed_prefix(left_over, 1).shape == (1, 10)
    assert committed_prefix(left_over, 0) is None
    assert committed_prefix(None, 3) is None
    assert committed_prefix(torch.zeros(10, 10), 3) is None
    with pytest.raises(ValueError, match="prev_chunk_left_over"):
        committed_prefix(torch.zeros(2, 3, 10), 2)


def test_sync_calls_are_unchanged():
    """Without the engine's arguments the chunk is the executed steps, as before."""
    policy = make_policy()
    chunk = policy.predict_action_chunk(random_observation(policy.config))
    assert chunk.shape == (1, policy.config.n_action_steps, 10)


def test_an_enforced_gate_s_flagged_chunk_holds_the_measured_pose(tmp_path):
    """Once the enforced gate flags a chunk, the engine receives the hold pose, never the flagged chunk."""
    policy = make_policy()
    policy.config.ood.enforce = True
    scores = np.full(50, 1e-9) * (1 + 1e-3 * np.random.default_rng(0).standard_normal(50))
    policy.ood_calibration = fit_calibration(scores, model="normal")
    obs = random_observation(policy.config, n_steps=0)
    chunk = policy.predict_action_chunk(obs, inference_delay=0, prev_chunk_left_over=None)
    assert policy.ood_status()["released"]
    hold = policy._hold_action(obs)
    torch.testing.assert_close(chunk, hold[:, None].expand_as(chunk))


def test_a_free_score_flags_before_the_inpainted_chunk_is_sampled_and_that_chunk_holds():
    """``rtc_score="free"``: the gate reads the free prediction first, so a flag waits for one prediction, and
    the inpainted chunk sampled after it is replaced by the hold pose."""
    policy = make_policy(rtc_score="free")
    policy.config.ood.enforce = True
    scores = np.full(50, 1e-9) * (1 + 1e-3 * np.random.default_rng(0).standard_normal(50))
    policy.ood_calibration = fit_calibration(scores, model="normal")
    released_when_inpainting, predict = [], policy.predict_action_distribution

    def recording(batch, **kwargs):
        if kwargs.get("prefix") is not None:
            released_when_inpainting.append(policy.ood_status()["released"])
        return predict(batch, **kwargs)

    policy.predict_action_distribution = recording
    obs = random_observation(policy.config, n_steps=0)
    chunk = policy.predict_action_chunk(obs, inference_delay=2, prev_chunk_left_over=padded_left_over(rows=5))
    assert released_when_inpainting == [True]
    torch.testing.assert_close(chunk, policy._hold_action(obs)[:, None].expand_as(chunk))


RTC_FPS = 20.0


def rtc_engine_on_the_arm(tiny_policy_dir, seed: int):
    """The tiny ensemble on LeRobot's own ``RTCInferenceEngine`` (background thread, action queue) over the
    simulated arm of scene ``seed``, fast clock, at ``RTC_FPS``: (policy, postprocessor, robot, engine), the robot
    connected and the engine not started. The policy is looked up at every call, so a test may wrap its
    ``predict_action_chunk`` afterwards."""
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.rtc.configuration_rtc import RTCConfig
    from lerobot.rollout.inference.rtc import RTCInferenceEngine
    from lerobot.rollout.robot_wrapper import ThreadSafeRobot
    from lerobot.utils.feature_utils import hw_to_dataset_features
    from lerobot_robot_suture.config_suture_sim import SutureSimConfig
    from lerobot_robot_suture.suture_sim import SutureSim

    policy = EnsembleDiffusionPolicy.from_pretrained(tiny_policy_dir).eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy.config, pretrained_path=str(tiny_policy_dir)
    )
    image_size = policy.config.image_features["observation.images.endoscope"].shape[-1]
    robot = SutureSim(SutureSimConfig(seed=seed, clock="fast", image_size=image_size))
    robot.connect()
    engine = RTCInferenceEngine(
        policy,
        preprocessor,
        postprocessor,
        ThreadSafeRobot(robot),
        RTCConfig(execution_horizon=policy.config.horizon),
        hw_to_dataset_features(robot.observation_features, "observation"),
        "Insert the needle.",
        RTC_FPS,
        "cpu",
        rtc_queue_threshold=policy.config.horizon - 2,
    )
    return policy, postprocessor, robot, engine


def test_lerobot_s_rtc_engine_on_the_arm_respects_prefixes_and_never_executes_a_flagged_chunk(
    tiny_policy_dir,
):
    """LeRobot's own engine (background thread, action queue) runs the tiny ensemble on the simulated arm; the
    loop reads the gate after each action it takes from the queue, as ``gated_dagger`` does. The gate is made to
    flag the fourth chunk: none of that chunk's new actions reaches the arm, and every chunk after the first
    starts with the actions committed before it."""
    import threading
    import time

    from lerobot_robot_suture.rollout_gate import RolloutGate

    policy, postprocessor, robot, engine = rtc_engine_on_the_arm(tiny_policy_dir, seed=3)
    never = fit_calibration(1e9 * (1 + 1e-3 * np.random.default_rng(0).standard_normal(50)), model="normal")
    always = fit_calibration(1e-9 * (1 + 1e-3 * np.random.default_rng(0).standard_normal(50)), model="normal")
    policy.ood_calibration = never
    chunks, lock = [], threading.Lock()
    predict = policy.predict_action_chunk

    def recorded_predict(batch, inference_delay=None, prev_chunk_left_over=None):
        with lock:
            if len(chunks) == 3:  # the fourth chunk is flagged
                policy.ood_calibration, policy._ood_gates = always, []
        chunk = predict(batch, inference_delay=inference_delay, prev_chunk_left_over=prev_chunk_left_over)
        prefix = committed_prefix(prev_chunk_left_over, inference_delay)
        with lock:
            chunks.append((prefix, chunk.clone(), policy.ood_status()["decision"]))
        return chunk

    policy.predict_action_chunk = recorded_predict
    gate = RolloutGate(policy, "ensemble")
    sent, handed_over = [], False
    engine.start()
    engine.resume()
    try:
        deadline = time.perf_counter() + 60.0
        while time.perf_counter() < deadline:
            tick = time.perf_counter()
            obs = robot.get_observation()
            engine.notify_observation(obs)
            action = engine.get_action(None)
            if action is not None:
                if gate.read(obs).decision:
                    handed_over = True
                    break
                robot.send_action({key: float(action[i]) for i, key in enumerate(robot.action_features)})
                sent.append(action.clone())
            time.sleep(max(0.0, 1.0 / RTC_FPS - (time.perf_counter() - tick)))
    finally:
        engine.stop()
        robot.disconnect()
    assert handed_over and len(chunks) >= 4 and sent
    assert not any(flagged for *_, flagged in chunks[:3]) and chunks[3][2]
    delayed = [(prefix, chunk) for prefix, chunk, _ in chunks[1:] if prefix is not None]
    assert delayed, "the engine never reported an inference delay"
    for prefix, chunk in delayed:
        torch.testing.assert_close(chunk[0, : prefix.shape[0]], prefix, atol=1e-5, rtol=0)
    prefix, flagged_chunk, _ = chunks[3]
    committed = 0 if prefix is None else prefix.shape[0]
    new_actions = postprocessor(flagged_chunk)[0, committed:]
    for action in sent:
        assert not torch.isclose(new_actions, action[None], atol=1e-6, rtol=0).all(dim=-1).any()


def test_a_new_scene_s_first_chunk_is_predicted_from_that_scene(tiny_policy_dir):
    """``gated_dagger`` restarts LeRobot's real-time engine between scenes: the first chunk of the next scene is
    predicted from its own first observation, however long that observation takes to arrive, and not from the
    last frame of the scene before, the latest observation the engine was handed."""
    import threading
    import time

    from lerobot.utils.feature_utils import build_dataset_frame, hw_to_dataset_features
    from lerobot_robot_suture.gated_dagger import restart_engine

    from lerobot_suture.lerobot_shim import ExecutedActionQueue

    policy, _, robot, engine = rtc_engine_on_the_arm(tiny_policy_dir, seed=7)
    states, lock = [], threading.Lock()
    predict = policy.predict_action_chunk

    def recorded_predict(batch, inference_delay=None, prev_chunk_left_over=None):
        with lock:
            states.append(batch["observation.state"][0].clone())
        return predict(batch, inference_delay=inference_delay, prev_chunk_left_over=prev_chunk_left_over)

    policy.predict_action_chunk = recorded_predict
    features = hw_to_dataset_features(robot.observation_features, "observation")

    def run(ticks: int) -> None:
        for _ in range(ticks):
            obs = robot.get_observation()
            engine.notify_observation(obs)
            action = engine.get_action(None)
            if action is not None:
                robot.send_action({key: float(action[i]) for i, key in enumerate(robot.action_features)})
            time.sleep(1.0 / RTC_FPS)

    def normalized_state(obs) -> torch.Tensor:
        state = torch.as_tensor(build_dataset_frame(features, obs, prefix="observation")["observation.state"])
        return (state.float() - policy.state_unnormalize_offset) / policy.state_unnormalize_scale

    engine.start()
    engine.resume()
    try:
        run(ticks=12)  # scene 7: the arm moves
        engine.pause()
        robot.reset_scene(8)
        restart_engine(engine)
        assert isinstance(engine.action_queue, ExecutedActionQueue)
        with lock:
            before = len(states)
        engine.resume()
        time.sleep(
            0.3
        )  # a slow first camera read: the engine has had time to predict, had it anything to predict from
        first_obs = robot.get_observation()
        run(ticks=1)
        deadline = time.perf_counter() + 30.0
        while len(states) == before and time.perf_counter() < deadline:
            time.sleep(0.01)
    finally:
        engine.stop()
        robot.disconnect()
    assert len(states) > before, "the engine predicted nothing in the new scene"
    torch.testing.assert_close(states[before], normalized_state(first_obs), atol=1e-4, rtol=0)


@pytest.mark.parametrize("queue_class", ["lerobot", "executed"])
def test_a_new_chunk_resumes_at_the_first_action_not_yet_executed(queue_class):
    """Two actions were taken while a chunk was predicted, and its latency's ceiling says three: the merged
    queue resumes at the new chunk's third action, the first not executed. LeRobot's own queue skips it."""
    from lerobot.policies.rtc import ActionQueue
    from lerobot.policies.rtc.configuration_rtc import RTCConfig

    from lerobot_suture.lerobot_shim import ExecutedActionQueue

    queue = (ActionQueue if queue_class == "lerobot" else ExecutedActionQueue)(RTCConfig(enabled=True))
    old = torch.arange(8.0)[:, None].expand(8, 2).clone()
    queue.merge(old, old, real_delay=0, action_index_before_inference=0)
    queue.get(), queue.get()  # the arm executes two actions of the old chunk
    before = queue.get_action_index()
    queue.get(), queue.get()  # two more while the new chunk is predicted
    new = 100 + torch.arange(8.0)[:, None].expand(8, 2)
    queue.merge(new, new, real_delay=3, action_index_before_inference=before)
    expected = 102.0 if queue_class == "executed" else 103.0  # LeRobot 0.6.1 drops one action too many
    assert float(queue.get()[0]) == expected


def test_the_executed_action_queue_is_put_on_a_real_time_engine_only():
    from lerobot.policies.rtc import ActionQueue
    from lerobot.policies.rtc.configuration_rtc import RTCConfig

    from lerobot_suture.lerobot_shim import ExecutedActionQueue, merge_after_executed_actions

    class Engine:
        action_queue = ActionQueue(RTCConfig(enabled=True))

    engine = Engine()
    merge_after_executed_actions(engine)
    assert type(engine.action_queue) is ExecutedActionQueue
    merge_after_executed_actions(object())  # the sync engine has no queue: nothing to do
