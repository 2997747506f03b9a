"""The command line (``facepipe``): click commands, previews and their renderer."""

__all__ = ["cli", "main"]


def main(argv=None) -> None:
    """Console entry point (:func:`facepipe.cli.commands.main`). Started as a command (no
    ``argv``), the process first restarts itself with large pages for the heap where that helps
    (:mod:`facepipe.cli.large_pages`), before the commands' imports."""
    if argv is None:
        from facepipe.cli.large_pages import restart_with_large_pages

        restart_with_large_pages()
    from facepipe.cli.commands import main as run

    run(argv)


def __getattr__(name):
    if name == "cli":  # the click group, imported on first use: the start stays light
        from facepipe.cli.commands import cli

        return cli
    raise AttributeError(f"module 'facepipe.cli' has no attribute {name!r}")
