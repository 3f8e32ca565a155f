"""The README's tool chains, run verbatim: OpenMVG's front end -> `rotonly run` -> OpenMVG's
ComputeStructureFromKnownPoses, ComputeSfM_DataColor and openMVG2Colmap; COLMAP's front end ->
`rotonly run` -> COLMAP's model_analyzer and image_undistorter. Every step must exit 0.

The images are rendered here (textured walls, floor and a box seen by eight cameras with a
known K), so the test needs no data; ``ROTONLY_CHAIN_IMAGES`` (a folder of images) with
``ROTONLY_CHAIN_K`` (OpenMVG's "f;0;cx;0;f;cy;0;0;1") and ``ROTONLY_CHAIN_CAM`` (COLMAP's
"fx,fy,cx,cy") runs the chains on real images instead. The OpenMVG chain needs OpenMVG's
tools (``ROTONLY_OPENMVG_BIN``: their bin folder), the COLMAP chain the ``colmap`` command;
each is skipped without them."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import REPOSITORY

OPENMVG_BIN = os.environ.get("ROTONLY_OPENMVG_BIN", "")
WIDTH, HEIGHT, FOCAL = 480, 360, 450.0
#: principal point at the image centre: OpenMVG's pixel convention (pixel centres at integers)
CX, CY = (WIDTH - 1) / 2, (HEIGHT - 1) / 2


def readme_block(marker: str) -> str:
    """The README's ```bash block holding ``marker``."""
    blocks = re.findall(r"```bash\n(.*?)```", (REPOSITORY / "README.md").read_text(), re.S)
    found = [block for block in blocks if marker in block]
    assert len(found) == 1, marker
    return found[0]


def _texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """Multi-scale noise with blobs and boxes: plenty of SIFT features at every scale."""
    import cv2

    image = np.zeros((size, size), dtype=np.float32)
    for scale, weight in ((16, 1.0), (64, 1.0), (256, 0.8)):
        coarse = rng.uniform(size=(size // scale + 1, size // scale + 1)).astype(np.float32)
        image += weight * cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC)
    image = (image - image.min()) / np.ptp(image)
    for _ in range(300):
        x, y = (int(v) for v in rng.integers(0, size, 2))
        r, value = int(rng.integers(4, 24)), float(rng.uniform())
        if rng.uniform() < 0.5:
            cv2.circle(image, (x, y), r, value, -1)
        else:
            cv2.rectangle(image, (x, y), (x + r, y + 2 * r // 3), value, -1)
    return np.clip(255 * image, 0, 255).astype(np.uint8)


#: rectangles: corner, two edge vectors (world units; y points down, the cameras look along +z)
SURFACES = (
    ((-10.0, -7.0, 12.0), (20.0, 0.0, 0.0), (0.0, 10.0, 0.0)),   # back wall
    ((-10.0, 3.0, 2.0), (20.0, 0.0, 0.0), (0.0, 0.0, 10.0)),     # floor
    ((-7.0, -7.0, 2.0), (0.0, 0.0, 10.0), (0.0, 10.0, 0.0)),     # left wall
    ((-1.0, 0.5, 8.0), (3.0, 0.0, 0.0), (0.0, 2.5, 0.0)),        # box, front
    ((2.0, 0.5, 8.0), (0.0, 0.0, 2.0), (0.0, 2.5, 0.0)),         # box, side
)


def cameras(count: int = 8) -> list[tuple[np.ndarray, np.ndarray]]:
    """(R_cam_from_world, centre) along a gentle arc, all looking at the scene's middle."""
    poses = []
    for k, x in enumerate(np.linspace(-2.2, 2.2, count)):
        centre = np.array([x, -0.4 + 0.15 * np.sin(k), 0.3 * np.cos(0.7 * k)])
        forward = np.array([0.25 * x, 0.6, 10.0]) - centre
        forward /= np.linalg.norm(forward)
        right = np.cross([0.0, 1.0, 0.0], forward)
        right /= np.linalg.norm(right)
        poses.append((np.stack([right, np.cross(forward, right), forward]), centre))
    return poses


def render(folder: Path, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Eight JPEGs of the textured scene in ``folder``; returns their poses."""
    import cv2

    rng = np.random.default_rng(seed)
    textures = [_texture(rng) for _ in SURFACES]
    folder.mkdir(parents=True)
    u, v = np.meshgrid(np.arange(WIDTH, dtype=float), np.arange(HEIGHT, dtype=float))
    rays_cam = np.stack([(u - CX) / FOCAL, (v - CY) / FOCAL, np.ones_like(u)], axis=-1)
    poses = cameras()
    for index, (R, centre) in enumerate(poses):
        rays = rays_cam @ R  # world directions (R^T d per pixel)
        depth = np.full((HEIGHT, WIDTH), np.inf)
        image = np.zeros((HEIGHT, WIDTH), dtype=np.float32)
        for (corner, edge_a, edge_b), texture in zip(SURFACES, textures):
            corner, edge_a, edge_b = (np.asarray(a) for a in (corner, edge_a, edge_b))
            normal = np.cross(edge_a, edge_b)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((corner - centre) @ normal) / (rays @ normal)
                hit = centre + t[..., None] * rays - corner
                s = hit @ edge_a / (edge_a @ edge_a)
                r = hit @ edge_b / (edge_b @ edge_b)
            visible = (t > 0) & (t < depth) & (s >= 0) & (s <= 1) & (r >= 0) & (r <= 1)
            size = texture.shape[0] - 1
            sampled = cv2.remap(texture, (s * size).astype(np.float32), (r * size).astype(np.float32),
                                cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
            image[visible] = sampled[visible]
            depth[visible] = t[visible]
        colour = np.stack([image, 0.8 * image + 30, 0.6 * image + 60], axis=-1)
        cv2.imwrite(str(folder / f"{index:04d}.jpg"), np.clip(colour, 0, 255).astype(np.uint8),
                    [cv2.IMWRITE_JPEG_QUALITY, 95])
    return poses


def _images(cwd: Path) -> tuple[list | None, str, str]:
    """``cwd/images`` (rendered, or ROTONLY_CHAIN_IMAGES copied) -> (poses or None, K, CAM)."""
    real = os.environ.get("ROTONLY_CHAIN_IMAGES")
    if real:
        shutil.copytree(real, cwd / "images")
        return None, os.environ["ROTONLY_CHAIN_K"], os.environ["ROTONLY_CHAIN_CAM"]
    poses = render(cwd / "images")
    return (poses, f"{FOCAL};0;{CX};0;{FOCAL};{CY};0;0;1", f"{FOCAL},{FOCAL},{CX + 0.5},{CY + 0.5}")


def _run(block: str, cwd: Path, **variables: str) -> subprocess.CompletedProcess:
    """``block`` as written, in bash -e (every step must exit 0), with ``rotonly`` on PATH."""
    env = {**os.environ, **variables, "QT_QPA_PLATFORM": "offscreen",
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    result = subprocess.run(["bash", "-e", "-x", "-c", block], cwd=cwd, env=env, capture_output=True, text=True,
                            timeout=3600)
    assert result.returncode == 0, result.stderr[-4000:]
    return result


def _rotation_errors_deg(out: Path, poses: list) -> np.ndarray:
    """Geodesic errors of OUT/sfm_data.json's relative rotations to the first view."""
    document = json.loads((out / "sfm_data.json").read_text())
    name_of = {item["value"]["ptr_wrapper"]["data"]["id_pose"]: item["value"]["ptr_wrapper"]["data"]["filename"]
               for item in document["views"]}
    estimated = {name_of[item["key"]]: np.array(item["value"]["rotation"]) for item in document["extrinsics"]}
    truth = {f"{k:04d}.jpg": R for k, (R, _) in enumerate(poses)}
    assert estimated.keys() == truth.keys()
    first = "0000.jpg"
    errors = []
    for name in truth:
        relative_est = estimated[name] @ estimated[first].T
        relative_true = truth[name] @ truth[first].T
        cos = (np.trace(relative_est.T @ relative_true) - 1) / 2
        errors.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.array(errors)


@pytest.mark.skipif(not (OPENMVG_BIN and Path(OPENMVG_BIN, "openMVG_main_SfMInit_ImageListing").is_file()),
                    reason="OpenMVG's tools not found (set ROTONLY_OPENMVG_BIN to their bin folder)")
def test_readme_openmvg_chain(tmp_path):
    poses, K, _ = _images(tmp_path)
    _run(readme_block("openMVG_main_SfMInit_ImageListing"), tmp_path, B=OPENMVG_BIN, K=K)
    out, project = tmp_path / "OUT", tmp_path / "P"
    document = json.loads((out / "sfm_data.json").read_text())
    assert document["root_path"] == "images"  # as SfMInit_ImageListing wrote it
    load = json.loads((out / "reports" / "load.json").read_text())
    assert load["matches_file"] == "P/matches.e.bin"
    triangulate = json.loads((out / "reports" / "triangulate.json").read_text())
    assert triangulate["images_missing"] == [] and triangulate["points_coloured"] > 0
    assert (out / "report.html").is_file()
    robust = json.loads((project / "robust.json").read_text())
    assert len(robust["extrinsics"]) == len(document["extrinsics"]) and len(robust["structure"]) > 100
    assert (project / "colored.ply").stat().st_size > 1000
    assert all((project / name).is_file() for name in ("cameras.txt", "images.txt", "points3D.txt"))
    if poses is not None:
        assert len(document["extrinsics"]) == len(poses)
        assert _rotation_errors_deg(out, poses).max() < 0.5


@pytest.mark.skipif(not (OPENMVG_BIN and Path(OPENMVG_BIN, "openMVG_main_SfMInit_ImageListing").is_file()),
                    reason="OpenMVG's tools not found (set ROTONLY_OPENMVG_BIN to their bin folder)")
def test_readme_openmvg_chain_without_a_camera(tmp_path):
    """The README's OpenMVG chain as its comment says to run it without K and without EXIF
    (the rendered images have none): the listing leaves every intrinsic undefined, the matches
    are filtered with a fundamental matrix, and rotonly guesses the camera and calibrates it;
    OpenMVG's own tools take the sfm_data.json it writes. Always on the rendered images (real
    ones, ROTONLY_CHAIN_IMAGES, may carry an EXIF focal)."""
    poses = render(tmp_path / "images")
    block = readme_block("openMVG_main_SfMInit_ImageListing")
    block = block.replace(' -k "$K"', "").replace("-g e", "-g f").replace("matches.e.bin", "matches.f.bin")
    _run(block, tmp_path, B=OPENMVG_BIN)
    listed = json.loads((tmp_path / "P" / "sfm_data.json").read_text())
    assert listed["intrinsics"] == []  # no K, no EXIF: the listing leaves every view without a camera
    out = tmp_path / "OUT"
    document = json.loads((out / "sfm_data.json").read_text())
    (camera,) = document["intrinsics"]
    focal = camera["value"]["ptr_wrapper"]["data"]["focal_length"]
    assert abs(focal / FOCAL - 1) < 0.01
    robust = json.loads((tmp_path / "P" / "robust.json").read_text())
    assert len(robust["extrinsics"]) == len(document["extrinsics"]) == len(poses) and len(robust["structure"]) > 100
    assert _rotation_errors_deg(out, poses).max() < 0.5


@pytest.mark.skipif(shutil.which("colmap") is None, reason="COLMAP's command-line tool not installed")
def test_readme_colmap_chain(tmp_path):
    poses, _, cam = _images(tmp_path)
    _run(readme_block("colmap feature_extractor"), tmp_path, CAM=cam)
    out = tmp_path / "OUT"
    run = json.loads((out / "reports" / "run.json").read_text())
    assert run["num_registered"] == run["num_views"] and (out / "report.html").is_file()
    assert len(list((tmp_path / "dense" / "images").iterdir())) == run["num_registered"]
    if poses is not None:
        assert _rotation_errors_deg(out, poses).max() < 0.5
