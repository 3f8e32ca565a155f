"""`rotonly simulate twoview|multiview`: the paper's synthetic scenes, written to files."""

from __future__ import annotations

import logging
from pathlib import Path

import click

logger = logging.getLogger(__name__)

#: options of both scene kinds
noise = click.option("--noise", "noise_px", type=click.FloatRange(min=0), default=1.0, show_default=True,
                     help="Pixel noise n (default model: magnitude U(0, n), random direction).")
noise_model = click.option("--noise-model", type=click.Choice(["uniform", "gaussian", "opengv"]), default="uniform",
                           show_default=True)
seed = click.option("--seed", type=int, default=0, show_default=True)
focal = click.option("--focal", type=click.FloatRange(min=0, min_open=True), default=800.0, show_default=True,
                     help="Focal length (px).")
image_size = click.option("--image-size", type=click.IntRange(min=1), default=960, show_default=True,
                          help="Square image side (px).")


@click.group("simulate")
def command() -> None:
    """Generate the paper's synthetic two-view and multi-view scenes (with ground truth)."""


@command.command("twoview")
@click.option("--scene", type=click.Choice(["standard", "planar", "holoplane", "rankregular_line", "pure_rotation"]),
              default="standard", show_default=True,
              help="Scene structure (paper §Default Settings / §Scene Identification).")
@noise
@noise_model
@click.option("--points", "num_points", type=click.IntRange(min=6), default=1000, show_default=True)
@seed
@focal
@image_size
@click.option("-o", "--output", "output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Output .npz (ground truth included).")
def twoview(scene: str, noise_px: float, noise_model: str, num_points: int, seed: int, focal: float,
            image_size: int, output: Path) -> None:
    """One simulated edge: noisy normalized matches + true R_j_from_i, t_j_from_i and points."""
    from rotonly_cli.simulation.pair_scenes import save_twoview, simulate_twoview

    problem = simulate_twoview(scene, num_points=num_points, noise_px=noise_px, focal=focal,
                               image_size=image_size, rng=seed, noise_model=noise_model)
    path = save_twoview(output, problem)
    click.echo(f"{path}: scene={scene} points={problem.num_points} noise={noise_px}px "
               f"|t|={float((problem.t_j_from_i ** 2).sum() ** 0.5):.3f}")


@command.command("multiview")
@click.option("--setup", type=click.Choice(["circular", "square", "linear", "outward"]), default="circular",
              show_default=True)
@click.option("--views", "num_views", type=click.IntRange(min=3), default=100, show_default=True)
@click.option("--points", "num_points", type=click.IntRange(min=1), default=10_000, show_default=True)
@noise
@noise_model
@seed
@focal
@image_size
@click.option("--spacing", type=click.FloatRange(min=0, min_open=True), default=10.0, show_default=True,
              help="Distance between adjacent cameras (m).")
@click.option("--window", type=click.IntRange(min=1), default=10, show_default=True,
              help="Match cameras at most this many steps apart along the trajectory.")
@click.option("--min-shared", type=click.IntRange(min=5), default=30, show_default=True,
              help="Fewest shared points for a pair.")
@click.option("--init", type=click.Choice(["ransac", "perturbed", "truth"]), default="ransac", show_default=True,
              help="Initial relative rotations: 5-point RANSAC, GT rotated by --init-noise-deg, or GT.")
@click.option("--init-noise-deg", type=click.FloatRange(min=0), default=0.5, show_default=True)
@click.option("--corrupt-fraction", type=click.FloatRange(0, 1), default=0.0, show_default=True,
              help="Fraction of pairs given a random relative rotation (repeated-structure outliers).")
@click.option("--epipolar-outlier-fraction", type=click.FloatRange(0, 1), default=0.0, show_default=True,
              help="Fraction of every pair's matches moved 10-80 px along their epipolar line in the second view "
                   "(wrong matches that pass any two-view check).")
@click.option("--swapped-fraction", type=click.FloatRange(0, 1), default=0.0, show_default=True,
              help="Fraction of each view's points that trade image positions with a look-alike point within 40 px "
                   "(wrong observations shared by whole tracks).")
@click.option("--format", "formats", type=click.Choice(["colmap", "openmvg"]), multiple=True,
              default=("colmap", "openmvg"), show_default=True, help="Which input projects to write.")
@click.option("-o", "--output", "output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="New folder: database.db, openmvg/, gt/sfm_data.json, simulation.json.")
def multiview(setup: str, num_views: int, num_points: int, noise_px: float, noise_model: str, seed: int,
              focal: float, image_size: int, spacing: float, window: int, min_shared: int, init: str,
              init_noise_deg: float, corrupt_fraction: float, epipolar_outlier_fraction: float,
              swapped_fraction: float, formats: tuple[str, ...], output: Path) -> None:
    """A multi-view scene as a COLMAP database and an OpenMVG project, plus GT sfm_data.json."""
    from rotonly_cli.simulation.layout_scenes import save_multiview, simulate_multiview

    problem = simulate_multiview(setup, num_views=num_views, num_points=num_points, noise_px=noise_px,
                                 focal=focal, image_size=image_size, rng=seed, spacing=spacing, window=window,
                                 min_shared=min_shared, init=init, init_noise_deg=init_noise_deg,
                                 corrupt_fraction=corrupt_fraction, noise_model=noise_model,
                                 epipolar_outlier_fraction=epipolar_outlier_fraction,
                                 swapped_fraction=swapped_fraction)
    save_multiview(output, problem, formats=tuple(formats))
    click.echo(f"{output}: {setup} views={num_views} points={len(problem.points_in_world)} "
               f"pairs={len(problem.scene.pairs)} corrupted={len(problem.corrupted_pairs)}")
