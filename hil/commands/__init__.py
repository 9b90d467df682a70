"""Subcommands of `hil`: one module each, with ``register(subparsers)`` setting ``func``."""
