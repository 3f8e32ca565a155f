#!/usr/bin/env python
"""Probe: does rotonly hold on the OpenMVG projects a default user makes? The shared projects
were made with ComputeFeatures' HIGH preset; OpenMVG's default is NORMAL (3-4 times fewer
matches per pair, so the wrong matches of repeated structure weigh more). ``--describer``
picks another of ComputeFeatures' describers (AKAZE_FLOAT: noisier keypoints, less
distinctive descriptors). For each Strecha scene this builds a project from the scene's
images with OpenMVG 2.1's own tools and the given preset (kept under --work and reused), then
scores on its E-verified matches (and, with
``--filters e f``, on the F-verified ones a user without the intrinsics makes): rotonly (per
seed, with and without the reject stage's confirmation by tracks), OpenMVG's global SfM (E
only: its global engine needs them), and pycolmap's global mapper on the same matches written
as a COLMAP database.

    LD_LIBRARY_PATH=OPENMVG/lib python scripts/research/probe_openmvg_preset.py --root DATA/strecha \
        --openmvg-bin OPENMVG/bin --work WORK [--preset NORMAL] [--describer SIFT] [--focal-factor F] \
        [--seeds 0 1 2] [--filters e f]
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path


def project_commands(openmvg_bin: Path, images: Path, project: Path, K: str, preset: str,
                     describer: str = "SIFT") -> list[list[str]]:
    """OpenMVG 2.1's commands from images to E-verified matches (one camera: ``K`` as
    SfMInit_ImageListing's -k "f;0;cx;0;f;cy;0;0;1", or a bare focal length for its -f, which
    puts the principal point at the image centre as for an EXIF focal)."""
    tool = lambda name: str(openmvg_bin / f"openMVG_main_{name}")  # noqa: E731
    sfm_data, pairs = str(project / "sfm_data.json"), str(project / "pairs.bin")
    camera = ["-k", K] if ";" in K else ["-f", K]
    return [[tool("SfMInit_ImageListing"), "-i", str(images), "-o", str(project), *camera, "-c", "1"],
            [tool("ComputeFeatures"), "-i", sfm_data, "-o", str(project), "-m", describer, "-p", preset],
            [tool("PairGenerator"), "-i", sfm_data, "-o", pairs],
            [tool("ComputeMatches"), "-i", sfm_data, "-p", pairs, "-o", str(project / "matches.putative.bin")],
            [tool("GeometricFilter"), "-i", sfm_data, "-m", str(project / "matches.putative.bin"), "-g", "e",
             "-o", str(project / "matches.e.bin")]]


def shared_K(scene_dir: Path) -> str:
    """The shared project's camera as SfMInit_ImageListing's -k "f;0;cx;0;f;cy;0;0;1"."""
    data = json.loads((scene_dir / "openmvg" / "sfm_data.json").read_text())
    camera = data["intrinsics"][0]["value"]["ptr_wrapper"]["data"]
    f, (cx, cy) = camera["focal_length"], camera["principal_point"]
    return f"{f};0;{cx};0;{f};{cy};0;0;1"


def build_project(openmvg_bin: Path, scene_dir: Path, project: Path, preset: str, filters: list[str],
                  describer: str = "SIFT", focal_factor: float | None = None) -> None:
    """The project, with matches.<model>.bin for every geometric filter of ``filters``; a step
    whose product is there already is not run again (a kept project is reused). With
    ``focal_factor`` the camera is that factor times the GT focal, the principal point at the
    image centre, and every step (the E filter too) runs with it."""
    K = shared_K(scene_dir)
    if focal_factor is not None:
        K = f"{focal_factor * float(K.split(';')[0]):.2f}"
    commands = project_commands(openmvg_bin, scene_dir / "images", project, K, preset, describer)
    filtered = commands[-1]
    commands += [[*filtered[:filtered.index("-g") + 1], model, "-o", str(project / f"matches.{model}.bin")]
                 for model in filters if model != "e"]
    # what each step leaves: the listing's sfm_data.json, the describer's image_describer.json,
    # else the file it writes
    products = [project / "sfm_data.json", project / "image_describer.json"] + \
        [Path(command[command.index("-o") + 1]) for command in commands[2:]]
    project.mkdir(parents=True, exist_ok=True)
    with open(project / "build.log", "a") as log:
        for command, product in zip(commands, products):
            if product.exists():
                continue
            log.write(f"$ {' '.join(command)}\n")
            log.flush()
            subprocess.run(command, stdout=log, stderr=subprocess.STDOUT, check=True)


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from tool_runs import rotations_scene, run_openmvg_global

    import rotonly_cli
    from rotonly_cli.baselines.references import pycolmap_global_mapper
    from rotonly_cli.evaluation.quality import evaluate
    from rotonly_cli.io.colmap import write_database
    from rotonly_cli.io.detect import read_ground_truth
    from rotonly_cli.io.openmvg import read_project
    from rotonly_cli.options import RunOptions

    from strecha_gt import add_scenes_arguments

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scenes_arguments(parser)
    parser.add_argument("--openmvg-bin", type=Path, required=True)
    parser.add_argument("--work", type=Path, required=True, help="where the projects are built (and reused)")
    parser.add_argument("--preset", default="NORMAL", choices=("NORMAL", "HIGH", "ULTRA"))
    parser.add_argument("--describer", default="SIFT", choices=("SIFT", "SIFT_ANATOMY", "AKAZE_FLOAT", "AKAZE_MLDB"),
                        help="ComputeFeatures' -m (projects: SCENE-DESCRIBER-PRESET, SIFT's SCENE-PRESET)")
    parser.add_argument("--focal-factor", type=float, default=None,
                        help="list the images with this factor x the GT focal and the principal point at the centre "
                             "(SfMInit_ImageListing -f, as for an EXIF focal; projects SCENE...-fF)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--filters", nargs="+", default=["e"], choices=("e", "f"),
                        help="GeometricFilter's models whose matches are scored")
    args = parser.parse_args(argv)
    logging.getLogger("rotonly_cli").setLevel(logging.ERROR)
    print("| scene | method | seed | registered | rotation (deg) | position (GT units) |")
    print("|---|---|---|---|---|---|")
    for name in args.scenes:
        scene_dir = args.root / name
        describer = "" if args.describer == "SIFT" else f"-{args.describer}"
        focal = "" if args.focal_factor is None else f"-f{args.focal_factor:g}"
        project = args.work / f"{name}{describer}-{args.preset}{focal}"
        build_project(args.openmvg_bin, scene_dir, project, args.preset, args.filters, args.describer,
                      args.focal_factor)
        gt = read_ground_truth(scene_dir)
        sfm_data = project / "sfm_data.json"
        for model in args.filters:
            matches = project / f"matches.{model}.bin"
            for seed in args.seeds:
                for label, options in (("rotonly", RunOptions(progress=False)),
                                       ("rotonly, no confirmation", RunOptions(progress=False))):
                    if label != "rotonly":
                        options = replace(options, reject=replace(options.reject, confirm_max_rounds=0))
                    result = rotonly_cli.run(sfm_data, gt=scene_dir, matches=matches, seed=seed, options=options)
                    evaluation = result.evaluation
                    print(f"| {name} | {label}, {model} matches | {seed} | {len(result.rotations)} / {len(gt.poses)} | "
                          f"{evaluation['rotation_error_deg']['mean']:.4f} | "
                          f"{(evaluation.get('position_error') or {}).get('mean', float('nan')):.4f} |", flush=True)
            with tempfile.TemporaryDirectory(prefix="rotonly_preset_") as tmp:
                if model == "e":
                    own = run_openmvg_global(project, gt, args.openmvg_bin, Path(tmp), Path(tmp))
                    print(f"| {name} | OpenMVG 2.1 global SfM, e matches | - | {own.num_registered} / "
                          f"{len(gt.poses)} | {own.rotation_mean_deg:.4f} | {own.position_mean:.4f} |", flush=True)
                database = Path(tmp) / "database.db"
                write_database(database, read_project(sfm_data, None, matches))
                rotations = pycolmap_global_mapper(database)
                names = dict(enumerate(sorted(rotations)))
                mapper = evaluate(gt, rotations_scene(names, {k: rotations[n] for k, n in names.items()}))
                print(f"| {name} | pycolmap global mapper (K fixed), {model} matches | - | {mapper.num_matched} / "
                      f"{len(gt.poses)} | {mapper.rotation_error_deg.mean:.4f} | - |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
