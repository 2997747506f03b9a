"""The command line (``facepipe``): click commands, previews and their renderer."""

from facepipe.cli.commands import cli, main

__all__ = ["cli", "main"]
