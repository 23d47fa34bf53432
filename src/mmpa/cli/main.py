"""mmpa command-line interface (placeholder while the foundation lands)."""

import typer

app = typer.Typer(help="mmpa: precise mobile manipulation", no_args_is_help=True)


@app.command()
def version() -> None:
    """Print the mmpa version."""
    from mmpa import __version__

    typer.echo(__version__)
