"""`mapkit copy-store`."""

from __future__ import annotations

import click

from mapkit.cli._group import library_call, main


@main.command("copy-store")
@click.argument("source")
@click.argument("target")
@click.option("--overwrite", is_flag=True, help="Replace a complete store at TARGET.")
@library_call
def copy_store_cmd(source: str, target: str, overwrite: bool) -> None:
    """Copy a complete zarr store (frames.zarr, map.zarr, tuples.zarr) from SOURCE to TARGET, each a
    local path or an fsspec URL; published as the commands publish (root zarr.json last)."""
    from mapkit._stores import copy_store

    out = copy_store(source, target, overwrite=overwrite)
    click.echo(f"copied {source} to {out.url}")
