"""The pycolmap global mapper's error before and after its bundle adjustment (issue 51, item 2).

GLOMAP's stages are rotation averaging, global positioning (positions and points, the
rotations held) and bundle adjustment. ``--skip-ba`` runs it with
``GlobalMapperOptions.skip_bundle_adjustment`` (and no retriangulation, which only feeds the
BA), so the rotations written are rotation averaging's and the positions global
positioning's: what BA adds is the difference to the full run. Intrinsics held, as in
scripts/bench/tool_runs.run_global_mapper; evaluated like ``rotonly eval`` (mean
rotation error after the best global rotation, position error after the best similarity).
``--ba-from OUT/sparse``: instead, pycolmap's bundle adjustment (K fixed) started from
rotonly's COLMAP model (tool_runs.run_ba_on_rotonly): where a BA takes rotonly's own
poses and points on the same tracks.

    python scripts/research/probe_mapper_stages.py --database /work/scale/v200/database.db \\
        --gt /work/scale/v200/gt/sfm_data.json [--skip-ba] [--threads 1] [--ba-from OUT/sparse]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--database", type=Path, required=True)
    parser.add_argument("--gt", type=Path, required=True)
    parser.add_argument("--skip-ba", action="store_true")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ba-from", type=Path, help="rotonly's COLMAP model (OUT/sparse): BA from it instead")
    args = parser.parse_args(argv)
    import pycolmap

    from rotonly_cli.evaluation.quality import evaluate
    from rotonly_cli.pipeline import load_ground_truth

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from tool_runs import reconstruction_scene, run_ba_on_rotonly

    if args.ba_from is not None:
        result = run_ba_on_rotonly("rotonly run", args.ba_from, load_ground_truth(args.gt))
        print(f"| {result.method} | rotation mean {result.rotation_mean_deg:.5f} deg | position mean "
              f"{result.position_mean:.5f} | {result.time_s:.0f} s |")
        return 0

    pycolmap.logging.minloglevel = 2
    options = pycolmap.GlobalPipelineOptions()
    options.random_seed = args.seed
    options.num_threads = args.threads
    options.mapper.random_seed = args.seed
    options.mapper.num_threads = args.threads
    options.mapper.bundle_adjustment.refine_focal_length = False
    options.mapper.bundle_adjustment.refine_principal_point = False
    options.mapper.bundle_adjustment.refine_extra_params = False
    if args.skip_ba:
        options.mapper.skip_bundle_adjustment = True
        options.mapper.skip_retriangulation = True
    with tempfile.TemporaryDirectory(prefix="probe_mapper_") as tmp:
        work = Path(tmp)
        shutil.copyfile(args.database, work / "database.db")  # opening rewrites the header
        (work / "images").mkdir()
        (work / "models").mkdir()
        start = time.perf_counter()
        models = pycolmap.global_mapping(work / "database.db", work / "images", work / "models", options)
        call = time.perf_counter() - start
        best = max(models.values(), key=lambda r: r.num_reg_images())
        report = evaluate(load_ground_truth(args.gt), reconstruction_scene(best))
    label = "RA + GP (no BA)" if args.skip_ba else "RA + GP + BA"
    print(f"| pycolmap global mapper, {label} | {report.num_matched} views | rotation mean "
          f"{report.rotation_error_deg.mean:.5f} deg | position mean {report.position_error.mean:.5f} | "
          f"{call:.0f} s |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
