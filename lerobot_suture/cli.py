"""``lerobot-suture SUBCOMMAND --flag=value ...``: one entry point, LeRobot-style flags per subcommand.

Bad input (an unknown or missing subcommand, a bad flag, a missing policy, calibration or dataset) ends
with one line on stderr that names the problem and the fix, and exit status 2; Ctrl-C with 130.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from draccus.utils import DecodingError, DraccusException, ParsingError

# subcommand -> (module with `main(argv)`, or "module:function", one-line help)
SUBCOMMANDS = {
    "demo": ("lerobot_suture.demo", "run the main job at a small default and write figures"),
    "record": ("lerobot_suture.datasets.record", "record expert insertions as a LeRobotDataset"),
    "push": ("lerobot_suture.datasets.hub", "push a recorded dataset to the Hugging Face Hub"),
    "calibrate": (
        "lerobot_suture.calibrate",
        "fit the O.O.D. gate of a trained ensemble on nominal rollouts",
    ),
    # Lives in the policy plugin; imported by name only when run (the core never imports a plugin).
    "assemble": (
        "lerobot_policy_ensemble_diffusion.assemble",
        "assemble separately trained diffusion policies into one ensemble",
    ),
    "experiments": (
        "lerobot_suture.experiments.runner",
        "run the paper's experiments: figures, metrics, report",
    ),
    "score-study": (
        "lerobot_suture.experiments.score_study",
        "compare the gate's uncertainty scores on validation seeds",
    ),
    "benchmark-ood": (
        "lerobot_suture.experiments.benchmark_ood",
        "compare failure detectors (the gate's score and the field's) on the same rollouts",
    ),
    "robustness-report": (
        "lerobot_suture.experiments.robustness",
        "policies side by side under the shifts, inside and beyond their training ranges, with the gate",
    ),
    "reproduce": (
        "lerobot_suture.reproduce",
        "record, train, calibrate and run the experiments of a recipe (reference, robust, two_sided)",
    ),
    "dagger": (
        "lerobot_suture.dagger.loop",
        "learn from the surgeon in rounds: uncertainty-gated DAgger beside ungated DAgger and plain BC",
    ),
    "cbf-replay": (
        "lerobot_suture.experiments.cbf_offline",
        "filter a recorded unsafe throw offline, plot it",
    ),
    "surgeon-run": (
        "lerobot_suture.surgeon.commands:surgeon_run_main",
        "run a policy with a surgeon (keyboard, gamepad, expert) taking over; record it, show it live",
    ),
    "teleop": (
        "lerobot_suture.surgeon.commands:teleop_main",
        "drive the env by hand with a keyboard or gamepad; record it, show it live",
    ),
}


def _usage() -> str:
    lines = ["usage: lerobot-suture SUBCOMMAND [--flag=value ...]", "", "subcommands:"]
    lines += [f"  {name:14s} {help_}" for name, (_, help_) in SUBCOMMANDS.items()]
    lines += ["", "`lerobot-suture SUBCOMMAND --help` lists a subcommand's flags."]
    return "\n".join(lines)


def flag_error(exc: DraccusException | argparse.ArgumentError) -> str:
    """The useful line of a flag that draccus could not parse into a config (``exit_on_error=False``)."""
    if isinstance(exc, ParsingError) and not isinstance(exc, DecodingError) and exc.__cause__ is not None:
        return str(exc.__cause__)  # the config's own validation: it names the field and the allowed range
    return str(exc)  # "`field`: Couldn't parse 'x' into an int", "unrecognized arguments: --x=1", ...


def _fail(prefix: str, message: str) -> None:
    print(f"{prefix}: error: {' '.join(message.split())}", file=sys.stderr)  # one line, whatever the message
    raise SystemExit(2)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] in (["-h"], ["--help"]):
        print(_usage())
        return
    choices = f"one of {', '.join(SUBCOMMANDS)}; `lerobot-suture --help` says what each does"
    if not argv or argv[0].startswith("-"):
        _fail("lerobot-suture", f"a subcommand is required before any flag: {choices}.")
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        _fail("lerobot-suture", f"unknown subcommand {name!r}: choose {choices}.")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    module_name, _, function = SUBCOMMANDS[name][0].partition(":")
    run = getattr(importlib.import_module(module_name), function or "main")
    prefix = f"lerobot-suture {name}"
    try:
        run(rest)
    except (DraccusException, argparse.ArgumentError) as exc:
        _fail(prefix, f"{flag_error(exc)} (`{prefix} --help` lists the flags)")
    except (FileNotFoundError, FileExistsError, NotADirectoryError, ValueError) as exc:
        # Found past the flags: no policy, calibration or dataset where a flag points, or a setting the
        # loaded policy refuses. Each message says what to run or pass instead.
        _fail(prefix, str(exc))
    except KeyboardInterrupt:
        print(f"{prefix}: interrupted.", file=sys.stderr)
        raise SystemExit(130) from None


if __name__ == "__main__":
    main()
