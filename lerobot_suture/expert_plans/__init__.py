"""The scripted expert's plans for the tasks beyond ``insertion`` (whose plan is ``expert.ScriptedExpert``'s
own): ``pickup``, ``extraction`` and ``running_suture``, which strings the others together."""

import numpy as np


def episode_stream(seed: int | None, *keys: int) -> np.random.Generator:
    """A generator of the expert's own draws for the episode of env seed ``seed`` (``keys`` name the stream),
    apart from the env's draws; an unseeded env (None or < 0) gets fresh entropy."""
    return np.random.default_rng(None if seed is None or seed < 0 else [*keys[:1], seed, *keys[1:]])
