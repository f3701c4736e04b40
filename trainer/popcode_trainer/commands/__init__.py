"""Subcommands of ``popcode-train``, one module each."""
