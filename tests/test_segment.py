"""``lerobot-suture segment``: one subtask of recorded running sutures, each segment an episode of its own."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from lerobot_suture.datasets.segment import SegmentConfig, eval_split_fraction, subtask_runs
from lerobot_suture.sim.subtasks import SUBTASK_NAMES, SUBTASKS
from lerobot_suture.sim.wound_marks import MARKS_NAMES

NAMES = [*MARKS_NAMES, *SUBTASK_NAMES]


def labels(sequence: list[tuple[str, int]]) -> np.ndarray:
    rows = np.zeros((len(sequence), len(NAMES)), np.float32)
    for t, (subtask, throw) in enumerate(sequence):
        rows[t, len(MARKS_NAMES) + SUBTASKS.index(subtask)] = 1.0
        rows[t, -1] = throw
    return rows


def test_runs_are_cut_where_the_subtask_or_the_throw_changes():
    sequence = [("insert", 0)] * 3 + [("extract", 0)] * 2 + [("lay_down", 0), ("pick_up", 0)]
    sequence += [("insert", 1)] * 2 + [("insert", 2)] * 4 + [("extract", 2)]
    state = labels(sequence)
    assert subtask_runs(state, NAMES, "insert") == [(0, 3, 0), (7, 9, 1), (9, 13, 2)]
    assert subtask_runs(state, NAMES, "extract") == [(3, 5, 0), (13, 14, 2)]
    assert subtask_runs(state, NAMES, "pick_up") == [(6, 7, 0)]
    assert subtask_runs(labels([("lay_down", 0)] * 4), NAMES, "insert") == []


def test_the_eval_split_fraction_holds_out_exactly_the_validation_segments():
    for n in range(1, 400):
        for n_val in range(0, n):
            fraction = eval_split_fraction(n_val, n)
            assert math.ceil(n * fraction) == n_val, (n_val, n, fraction)


def test_bad_flags_are_refused_with_the_fix():
    with pytest.raises(ValueError, match="--source_root"):
        SegmentConfig()
    with pytest.raises(ValueError, match="`subtask` must be one of"):
        SegmentConfig(source_root="data", subtask="suture")
    with pytest.raises(ValueError, match="`min_frames`"):
        SegmentConfig(source_root="data", min_frames=0)
    assert (
        SegmentConfig(source_root="data/running/", subtask="extract").output_root().name == "running_extract"
    )


@pytest.mark.slow
def test_a_recorded_suture_is_cut_into_its_four_inserts_with_the_frames_as_recorded(tmp_path, capsys):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.cli import main as cli
    from lerobot_suture.datasets.features import ENV_STATE_KEY, IMAGE_KEY
    from lerobot_suture.datasets.metadata import read_episode_log
    from lerobot_suture.datasets.record import record, regenerate_episode
    from lerobot_suture.datasets.record_config import RecordConfig
    from lerobot_suture.datasets.segment import subtask_durations

    source = tmp_path / "running"
    common = dict(task="running_suture", image_size=32, val_fraction=0.5, marks=True)
    record(
        RecordConfig(repo_id="suture-tests/running", root=str(source), num_episodes=2, subtask=True, **common)
    )
    cli(["segment", f"--source_root={source}", "--subtask=insert"])
    root = tmp_path / "running_insert"
    log = read_episode_log(root)
    assert [(e["source_episode"], e["throw"]) for e in log["episodes"]] == [(0, t) for t in range(4)] + [
        (1, t) for t in range(4)
    ]
    assert log["splits"] == {"train": [0, 1, 2, 3], "val": [4, 5, 6, 7]}  # the suture's own split
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["splits"] == {"train": "0:4", "val": "4:8"} and info["total_episodes"] == 8
    assert math.ceil(8 * log["val_fraction"]) == 4
    assert "lerobot-suture segment --source_root=" in log["command"]
    durations = subtask_durations(source)  # the training suture's (episode 0) subtasks, for the stage budgets
    assert (
        len(durations["insert"]) == 4 and len(durations["extract"]) == 3
    )  # the last throw ends on its insert
    inserts = [e["length"] - 4 for e in log["episodes"][:3]]  # without the tail of what follows
    assert durations["insert"][:3] == inserts

    whole = LeRobotDataset("suture-tests/running", root=source)
    cut = LeRobotDataset("suture-tests/running_insert", root=root)
    assert cut.meta.video_keys == [IMAGE_KEY] and cut.fps == whole.fps
    for k, entry in enumerate(log["episodes"]):
        first = int(whole.meta.episodes[entry["source_episode"]]["dataset_from_index"]) + entry["from_frame"]
        start = int(cut.meta.episodes[k]["dataset_from_index"])
        assert int(cut.meta.episodes[k]["length"]) == entry["length"] > 1
        if entry["throw"] == 3:  # the suture ends with its last insert: nothing follows it
            tail = entry["length"]
            assert entry["from_frame"] + tail == int(whole.meta.episodes[entry["source_episode"]]["length"])
        else:
            tail = entry["length"] - 4  # the first of the four frames of the extract that follows
            # The insert ends on the action that opens the jaw, outside the last 4 frames
            # (drop_n_last_frames), so a training sample starts on it.
            assert float(cut[start + tail - 1]["action"][9]) < 0.5
        for t in sorted({0, tail - 1, min(tail, entry["length"] - 1), entry["length"] - 1}):
            a, b = cut[start + t], whole[first + t]
            for key in ("observation.state", ENV_STATE_KEY, "action"):
                np.testing.assert_array_equal(a[key].numpy(), b[key].numpy())
            assert a["task"] == b["task"] and a[ENV_STATE_KEY][-1] == entry["throw"]
            assert a[ENV_STATE_KEY][6 if t < tail else 7] == 1.0  # insert, then the extract's first frames
            # Encoded a second time: close to the recording, not bit for bit.
            assert float((a[IMAGE_KEY] - b[IMAGE_KEY]).abs().mean()) < 0.03

    def refused(argv: list[str], match: str) -> None:
        with pytest.raises(SystemExit) as exit_:
            cli(argv)
        assert exit_.value.code == 2 and match in capsys.readouterr().err

    refused(["segment", f"--source_root={source}", "--subtask=insert"], "or pass another --root")
    with pytest.raises(ValueError, match="regenerate episode 1 of that dataset"):
        regenerate_episode(root, 5)
    plain = tmp_path / "plain"
    record(
        RecordConfig(
            repo_id="suture-tests/plain", root=str(plain), num_episodes=1, **{**common, "val_fraction": 0}
        )
    )
    refused(["segment", f"--source_root={plain}", "--subtask=extract"], "--subtask=true")
    refused(
        ["segment", f"--source_root={tmp_path / 'none'}"], "not a dataset recorded by `lerobot-suture record`"
    )
    assert not (tmp_path / "plain_extract").exists()
