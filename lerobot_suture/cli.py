"""``lerobot-suture SUBCOMMAND --flag=value ...``: one entry point, LeRobot-style flags per subcommand.

Each subcommand is a module of :mod:`lerobot_suture.commands` with ``main(argv)``; this module reports
what they raise. Bad input (an unknown or missing subcommand, a bad flag, a missing policy, calibration
or dataset) ends with one line on stderr that names the problem and the fix, and exit status 2; an
error that carries its own ``exit_status`` (a failed push: 1) with that status; Ctrl-C with 130, or
128 + the signal's number where the interruption says which.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from draccus.utils import DecodingError, DraccusException, ParsingError

# subcommand -> (module with `main(argv)`, or "module:function", one-line help)
SUBCOMMANDS = {
    "demo": ("lerobot_suture.commands.demo", "run the main job at a small default and write figures"),
    "record": ("lerobot_suture.commands.record", "record expert insertions as a LeRobotDataset"),
    "segment": (
        "lerobot_suture.commands.segment",
        "cut recorded running sutures into one subtask's segments, each an episode of a new dataset",
    ),
    "push": ("lerobot_suture.commands.push", "push a recorded dataset to the Hugging Face Hub"),
    "calibrate": (
        "lerobot_suture.commands.calibrate",
        "fit the O.O.D. gate of a trained ensemble on nominal rollouts",
    ),
    "calibrate-stac": (
        "lerobot_suture.commands.calibrate_stac",
        "fit the STAC gate of any chunking policy (ACT, diffusion) on nominal rollouts",
    ),
    # Lives in the policy plugin; imported by name only when run (the core never imports a plugin).
    "assemble": (
        "lerobot_policy_ensemble_diffusion.assemble",
        "assemble separately trained diffusion policies into one ensemble",
    ),
    "chain": (
        "lerobot_policy_suture_chain.assemble",
        "chain trained policies under the running suture's high level (policy type suture_chain)",
    ),
    "experiments": (
        "lerobot_suture.commands.experiments",
        "run the paper's experiments: figures, metrics, report",
    ),
    # The studies live in their own distribution (./studies), imported by name only when run.
    "score-study": (
        "lerobot_suture_studies.commands.score_study",
        "compare the gate's uncertainty scores on validation seeds",
    ),
    "benchmark-ood": (
        "lerobot_suture_studies.commands.benchmark_ood",
        "compare failure detectors (the gate's score and the field's) on the same rollouts",
    ),
    "robustness-report": (
        "lerobot_suture_studies.commands.robustness_report",
        "policies side by side under the shifts, inside and beyond their training ranges, with the gate",
    ),
    "reproduce": (
        "lerobot_suture.commands.reproduce",
        "record, train, calibrate and run the experiments of a recipe (reference, robust, two_sided)",
    ),
    "leaderboard": (
        "lerobot_suture.commands.leaderboard",
        "rank LeRobot's ACT and diffusion and the ensemble on every task, 50 episodes a cell; add your own",
    ),
    "dagger": (
        "lerobot_suture.commands.dagger",
        "learn from the surgeon in rounds: uncertainty-gated DAgger beside ungated DAgger and plain BC",
    ),
    "cbf-replay": (
        "lerobot_suture.commands.cbf_replay",
        "filter a recorded unsafe throw offline, plot it",
    ),
    "surgeon-run": (
        "lerobot_suture.commands.surgeon_run",
        "run a policy with a surgeon (keyboard, gamepad, expert) taking over; record it, show it live",
    ),
    "teleop": (
        "lerobot_suture.commands.teleop",
        "drive the env by hand with a keyboard or gamepad; record it, show it live",
    ),
}


# The distributions, apart from this one, that a subcommand may live in: where their source is.
DISTRIBUTIONS = {"lerobot_policy_ensemble_diffusion": "./policies", "lerobot_suture_studies": "./studies"}


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


def _fail(prefix: str, message: str, status: int = 2) -> None:
    print(f"{prefix}: error: {' '.join(message.split())}", file=sys.stderr)  # one line, whatever the message
    raise SystemExit(status)


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
    prefix = f"lerobot-suture {name}"
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        distribution = (exc.name or "").split(".")[0]
        if distribution not in DISTRIBUTIONS:
            raise
        _fail(
            prefix,
            f"this subcommand lives in the {distribution} distribution, which is not installed: run "
            f"`pip install -e {DISTRIBUTIONS[distribution]}` from the repository (`make install` does).",
        )
    run = getattr(module, function or "main")
    try:
        run(rest)
    except (DraccusException, argparse.ArgumentError) as exc:
        _fail(prefix, f"{flag_error(exc)} (`{prefix} --help` lists the flags)")
    except KeyboardInterrupt as exc:
        print(f"{prefix}: interrupted{f' ({exc})' if str(exc) else ''}.", file=sys.stderr)
        raise SystemExit(getattr(exc, "exit_status", 130)) from None
    except Exception as exc:
        status = getattr(exc, "exit_status", None)
        if status is not None:  # an error that knows how the command ends (a failed push)
            _fail(prefix, str(exc), status)
        if isinstance(exc, FileNotFoundError | FileExistsError | NotADirectoryError | ValueError):
            # Found past the flags: no policy, calibration or dataset where a flag points, or a setting
            # the loaded policy refuses. Each message says what to run or pass instead.
            _fail(prefix, str(exc))
        raise


if __name__ == "__main__":
    main()
