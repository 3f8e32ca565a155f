"""The chain in memory: run (the Run every stage shares), stages (the stage calls and the plain
load stage), reject (the reject stage's rounds), calibrate (--intrinsics: the calibration as a
controller around the load stage and the passes of the chain). pipeline.py runs it into a
workspace (files, OUT handling, stage subcommands)."""

from rotonly_cli.chain.calibrate import ESTIMATION_LOAD, ESTIMATION_STAGES, calibrated_chain, load_scene, load_stage
from rotonly_cli.chain.run import Run, image_root, output_root_path, output_scene
from rotonly_cli.chain.stages import (
    STAGE_FUNCTIONS,
    average_stage,
    identify_stage,
    load_graph,
    optimize_stage,
    refine_stage,
    reject_stage,
    run_chain,
    translate_stage,
    triangulate_stage,
)
from rotonly_cli.stages import STAGES

__all__ = ["ESTIMATION_LOAD", "ESTIMATION_STAGES", "STAGES", "STAGE_FUNCTIONS", "Run", "average_stage",
           "calibrated_chain", "identify_stage", "image_root", "load_graph", "load_scene", "load_stage",
           "optimize_stage", "output_root_path", "output_scene", "refine_stage", "reject_stage", "run_chain",
           "translate_stage", "triangulate_stage"]
