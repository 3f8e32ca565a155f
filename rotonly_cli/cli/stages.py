"""The pipeline stages one by one on an OUT workspace (see `rotonly run`).

    rotonly identify INPUT -o OUT    # load + relative poses + scene identification -> OUT
    rotonly refine OUT               # TRRM on every active edge
    rotonly average OUT              # robust rotation averaging (+ outlier filter)
    rotonly optimize OUT             # GRRM
    rotonly translate OUT            # LiGT camera centres
    rotonly reject OUT               # multi-view outlier rejection, then GRRM + LiGT again
    rotonly triangulate OUT          # points; writes OUT/sfm_data.json and OUT/sparse/

Each updates OUT/state.npz, OUT/view_graph.json and OUT/reports/<stage>.json.
"""

from __future__ import annotations

from pathlib import Path

import click

from rotonly_cli.cli import options as cli_options
from rotonly_cli.cli.run import chain_command, echo_summary, run_options

identify = chain_command("identify", """Load INPUT (COLMAP .db or OpenMVG sfm_data.json), estimate the view graph and
    identify every edge's scene kind (REGULAR / PURE_ROTATION / ROTATION_SINGULAR) into OUT.""",
                         ("load", "identify"), cli_options.load_options, cli_options.max_memory)


def _stage_command(stage: str, summary: str, *options):
    """`rotonly <stage> WORKSPACE [options]`: one stage on an OUT workspace, in place."""
    def callback(ctx: click.Context, workspace: Path, **settings) -> None:
        from rotonly_cli.pipeline import resume

        echo_summary(resume(workspace, stage, run_options(ctx, **settings)), workspace)

    for option in reversed(options):
        callback = option(callback)
    callback = click.argument("workspace", metavar="WORKSPACE", type=click.Path(path_type=Path))(callback)
    callback = click.pass_context(callback)
    return click.command(stage, help=f"{summary}\n\nWORKSPACE is an OUT folder made by `rotonly identify` or "
                         "`rotonly run`; its state.npz, view_graph.json and "
                         f"reports/{stage}.json are updated in place.")(callback)


average = _stage_command("average", "Robust rotation averaging (L1 + IRLS, weighted by inlier count) of the "
                         "active edges; edges beyond --max-residual-deg are filtered.", cli_options.max_residual_deg)
optimize = _stage_command("optimize", "GRRM (the paper's Algorithm 4) refines the averaged global rotations on the "
                          "reprojection residuals of all REGULAR edges.", cli_options.jobs)
translate = _stage_command("translate", "Camera centres by LiGT from the rotations and the tracks of the REGULAR "
                           "edges.", cli_options.jobs)
reject = _stage_command("reject", "Drop the matches inconsistent with the global poses (Sampson error under the "
                        "rotations and LiGT centres), then run GRRM and LiGT again, until nothing changes.",
                        cli_options.jobs)
triangulate = _stage_command("triangulate", "Triangulate the tracks and write OUT/sfm_data.json and OUT/sparse/.",
                             cli_options.image_path, cli_options.gt, cli_options.jobs)

commands = {"identify": identify, "average": average, "optimize": optimize, "translate": translate,
            "reject": reject, "triangulate": triangulate}
