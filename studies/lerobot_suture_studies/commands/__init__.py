"""The studies' subcommands of ``lerobot-suture``, each a module with ``main(argv)``."""
