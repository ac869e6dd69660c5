"""Subcommands of the `dmesh` console script, one module each (discovered by eval.cli)."""
