"""``lerobot-suture SUBCOMMAND --flag=value ...``: one entry point, LeRobot-style flags per subcommand."""

from __future__ import annotations

import importlib
import logging
import sys

from draccus.utils import ParsingError

# subcommand -> (module with `main(argv)`, one-line help)
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
    "reproduce": (
        "lerobot_suture.reproduce",
        "record, train, calibrate and run the experiments with the reference recipe; compare the table",
    ),
    "cbf-replay": (
        "lerobot_suture.experiments.cbf_offline",
        "filter a recorded unsafe throw offline, plot it",
    ),
}


def _usage() -> str:
    lines = ["usage: lerobot-suture SUBCOMMAND [--flag=value ...]", "", "subcommands:"]
    lines += [f"  {name:14s} {help_}" for name, (_, help_) in SUBCOMMANDS.items()]
    lines += ["", "`lerobot-suture SUBCOMMAND --help` lists a subcommand's flags."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"lerobot-suture: unknown subcommand {name!r}.\n\n{_usage()}", file=sys.stderr)
        raise SystemExit(2)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    module = importlib.import_module(SUBCOMMANDS[name][0])
    try:
        module.main(rest)
    except ParsingError as exc:
        # A config's own validation error is the useful part; draccus wraps it.
        print(f"lerobot-suture {name}: {exc.__cause__ or exc}", file=sys.stderr)
        raise SystemExit(2) from exc


if __name__ == "__main__":
    main()
