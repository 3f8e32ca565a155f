"""`rotonly convert INPUT -o OUTPUT`: COLMAP database/model <-> OpenMVG project/sfm_data.json."""

from __future__ import annotations

from pathlib import Path

import click

from rotonly_cli.cli import options as cli_options


@click.command("convert")
@click.argument("input_path", metavar="INPUT", type=click.Path(path_type=Path))
@click.option("-o", "--output", "output_path", required=True, type=click.Path(path_type=Path),
              help="*.db: COLMAP database; *.json: OpenMVG sfm_data.json; otherwise a folder "
                   "(OpenMVG project for COLMAP input, COLMAP model for OpenMVG input).")
@cli_options.matches_dir
@cli_options.matches_file
@click.option("--text", is_flag=True, help="Write a COLMAP model as .txt instead of .bin.")
def command(input_path: Path, output_path: Path, matches_dir: Path | None, matches: Path | None,
            text: bool) -> None:
    """Convert between COLMAP and OpenMVG.

    \b
    INPUT (detected by content)     OUTPUT
    COLMAP database (SQLite)        folder -> OpenMVG project (sfm_data.json, .feat, matches.e.bin)
                                    *.json -> sfm_data.json (views, intrinsics)
    OpenMVG sfm_data.json (+ .feat, matches.*)
                                    *.db   -> COLMAP database (verified pairs -> two_view_geometries)
                                    folder -> COLMAP sparse model (needs poses)
    COLMAP model folder             *.json -> sfm_data.json (poses, structure)
                                    folder -> OpenMVG project

    Keypoints keep COLMAP's pixel convention inside rotonly; OpenMVG files get -0.5. Cameras
    OpenMVG cannot represent exactly (fx != fy, ...) become an undistorted pinhole with the
    keypoints re-rendered, so normalized coordinates are unchanged. Outputs are written
    atomically; inputs are never modified.
    """
    from rotonly_cli.convert import convert

    click.echo(convert(input_path, output_path, matches_dir=matches_dir, matches_file=matches, text=text),
               err=True)
