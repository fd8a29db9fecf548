"""One module per ``lerobot-suture`` subcommand: its ``main(argv)`` parses the flags into the job's config,
runs the job and prints what a person reads. The jobs themselves live below (the runtime layer and the
domain packages); nothing imports a command but :mod:`lerobot_suture.cli`, which reports their errors."""
