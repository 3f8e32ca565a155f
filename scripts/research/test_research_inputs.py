"""Tests of the research scripts that build inputs and probe them (scripts/research/README.md):
view subsets, sequential matching, wrong intrinsics, keypoint noise, panoramas, surveys, low
resolution, zoom, OpenMVG presets, long tracks. The GRRM probes' tests are in test_research.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rotonly_cli.geometry import so3
from rotonly_cli.scene.view_graph import Edge

from research_scripts import FIXTURES, ROOT, digest, load_script, load_script_at

probe_subsets = load_script("probe_view_subsets")
probe_intrinsics = load_script("probe_wrong_intrinsics")
probe_sequential = load_script("probe_sequential")
probe_noise = load_script("probe_keypoint_noise")


# ============================================================================ probe_view_subsets

def test_probe_view_subsets_on_fixture(tmp_path, capsys):
    """Subsets of 5 of the Herz-Jesu fixture's 8 views: one row each, every view registered
    with a centre (a clean scene: each subset is a rigid, well-connected graph), errors in
    the fixture's range, none collapsed; the input is untouched."""
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "Herz-Jesus-P8").symlink_to(FIXTURES / "herzjesu_p8")
    before = digest(FIXTURES / "herzjesu_p8" / "database.db")
    assert probe_subsets.main(["--root", str(tmp_path / "root"), "--scene", "Herz-Jesus-P8", "--input", "database",
                               "--views", "5", "--trials", "2"]) == 0
    assert digest(FIXTURES / "herzjesu_p8" / "database.db") == before
    out = capsys.readouterr().out
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| ") and line[2].isdigit()]
    assert len(rows) == 2
    for cells in rows:
        assert len(cells[0].lstrip("| ").split()) == 5
        assert cells[1] == cells[2] == "5"
        assert 0.001 < float(cells[3]) < 0.1 and float(cells[4].rstrip(" |")) < 0.05
    assert "collapsed (> 0.5) 0;" in out


def test_probe_view_subsets_refuses_a_subset_larger_than_the_scene(tmp_path):
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "Herz-Jesus-P8").symlink_to(FIXTURES / "herzjesu_p8")
    with pytest.raises(SystemExit) as exc:
        probe_subsets.main(["--root", str(tmp_path / "root"), "--scene", "Herz-Jesus-P8", "--input", "database",
                            "--views", "9"])
    assert exc.value.code == 2


# ============================================================================ probe_sequential

def test_sequential_pairs_keep_the_band_of_the_name_order():
    from rotonly_cli.stages.load import read_input

    scene, _ = read_input(FIXTURES / "herzjesu_p8" / "database.db")
    rank = {v: r for r, v in enumerate(sorted(scene.views, key=lambda v: Path(scene.views[v].name).name))}
    for window in (1, 2):
        banded = probe_sequential.sequential_pairs(scene, window)
        assert set(banded.pairs) == {key for key in scene.pairs if abs(rank[key[0]] - rank[key[1]]) <= window}
        assert len(banded.pairs) == sum(8 - d for d in range(1, window + 1))  # 8 views, every pair matched
    assert len(scene.pairs) == 28  # the scene read is not changed


def test_probe_sequential_on_fixture(tmp_path, capsys):
    """The Herz-Jesu fixture matched to its next image only (a chain of 7 pairs): every view
    registered with a centre, errors in the fixture's range; the input is untouched."""
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "Herz-Jesus-P8").symlink_to(FIXTURES / "herzjesu_p8")
    before = digest(FIXTURES / "herzjesu_p8" / "database.db")
    assert probe_sequential.main(["--root", str(tmp_path / "root"), "--scenes", "Herz-Jesus-P8", "--inputs",
                                  "database", "--windows", "1"]) == 0
    assert digest(FIXTURES / "herzjesu_p8" / "database.db") == before
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| Herz")]
    assert len(rows) == 1
    cells = rows[0]
    assert cells[2:6] == ["1", "7", "8 / 8", "8"]
    assert 0.001 < float(cells[6]) < 0.05 and float(cells[7].rstrip(" |")) < 0.02


# ============================================================================ probe_wrong_intrinsics

def test_probe_wrong_intrinsics_on_fixture(tmp_path, capsys):
    """The Herz-Jesu fixture's database with COLMAP's guess, with its focal 5 % long but
    marked known and as COLMAP writes an EXIF camera (principal point at the centre), and its
    OpenMVG project with the focal 20 % long: a row each, every view
    registered, the focal calibrated to within 0.5 % and the principal point to a few pixels;
    the inputs are untouched."""
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "Herz-Jesus-P8").symlink_to(FIXTURES / "herzjesu_p8")
    before = digest(FIXTURES / "herzjesu_p8" / "database.db")
    assert probe_intrinsics.main(["--root", str(tmp_path / "root"), "--scenes", "Herz-Jesus-P8",
                                  "--factors", "1.2", "--db-factors", "1.05", "--exif-factors", "1.0"]) == 0
    assert digest(FIXTURES / "herzjesu_p8" / "database.db") == before
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| Herz")]
    assert [cells[0] for cells in rows] == ["| Herz-Jesus-P8 guessed db", "| Herz-Jesus-P8 db x1.05",
                                            "| Herz-Jesus-P8 exif db x1.0", "| Herz-Jesus-P8 omvg x1.2"]
    for cells in rows:
        assert cells[3] == "8/8" and float(cells[1]) < 0.1
        assert abs(float(cells[4])) < 0.5 and float(cells[5].rstrip(" |")) < 5.0


def test_lens_database_moves_the_keypoints_as_the_lens_and_keeps_their_rays(tmp_path):
    """``lens_database``: with the lens's camera (known) the written database normalizes
    back to the fixture's own rays, and its keypoints moved by k1 r³ f at the corners (a
    lens the camera does not know); with COLMAP's guess the camera says nothing of it."""
    from rotonly_cli.io.colmap import read_database

    scene = read_database(FIXTURES / "herzjesu_p8" / "database.db")
    known = read_database(probe_intrinsics.lens_database(scene, -0.1, tmp_path / "known.db", known=True))
    guessed = read_database(probe_intrinsics.lens_database(scene, -0.1, tmp_path / "guessed.db"))
    (camera,) = known.intrinsics.values()
    assert camera.model == "OPENCV" and camera.params[4] == -0.1 and camera.prior_focal
    (guess,) = guessed.intrinsics.values()
    assert guess.model == "SIMPLE_RADIAL" and guess.params[3] == 0.0 and not guess.prior_focal
    for v in scene.views:
        np.testing.assert_allclose(known.normalized[v], scene.normalized[v], atol=1e-6)  # float32 keypoints
        np.testing.assert_array_equal(guessed.keypoints[v], known.keypoints[v])
        radius = np.linalg.norm(scene.normalized[v], axis=1)
        moved = np.linalg.norm(known.keypoints[v] - scene.keypoints[v], axis=1)
        np.testing.assert_allclose(moved, 0.1 * radius ** 3 * np.linalg.norm(
            scene.normalized[v] * camera.params[:2], axis=1) / np.maximum(radius, 1e-12), rtol=1e-3, atol=1e-3)


def test_probe_keypoint_noise_on_fixture(tmp_path, capsys):
    """The Herz-Jesu fixture's database with 0.5 px of noise added to every keypoint: a row
    with every view, the rotation error a little above the clean run's 0.0193 deg, the
    bundle adjustment's reference and the global mapper's beside it; the fixture is untouched."""
    from rotonly_cli.io.colmap import read_database

    scene = read_database(FIXTURES / "herzjesu_p8" / "database.db")
    noisy = read_database(probe_noise.noisy_database(scene, 0.5, tmp_path / "noisy.db"))
    moved = np.concatenate([noisy.keypoints[v] - scene.keypoints[v] for v in scene.views])
    assert np.std(moved) == pytest.approx(0.5, rel=0.02)
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "Herz-Jesus-P8").symlink_to(FIXTURES / "herzjesu_p8")
    before = digest(FIXTURES / "herzjesu_p8" / "database.db")
    assert probe_noise.main(["--root", str(tmp_path / "root"), "--scenes", "Herz-Jesus-P8", "--noise-px", "0.5",
                             "--mapper"]) == 0
    assert digest(FIXTURES / "herzjesu_p8" / "database.db") == before
    (row,) = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| Herz")]
    assert row[2] == "8 / 8" and 0.0193 < float(row[3]) < 0.04 and 0.0 < float(row[5]) < 0.04
    mapper_error, mapper_registered = row[6].split(" (")
    assert 0.0 < float(mapper_error) < 0.04 and mapper_registered == "8 / 8)"


def test_probe_panorama_on_a_small_panorama(capsys):
    """Ten views turned 20° apart, the true focal and a guess x1.2: every view at one centre,
    every edge PURE_ROTATION, the guess calibrated back, and the threshold counts line."""
    probe_panorama = load_script("probe_panorama")
    assert probe_panorama.main(["--seeds", "1", "--views", "10", "--step-deg", "20", "--points", "3000",
                                "--focal-factors", "1.2"]) == 0
    out = capsys.readouterr().out
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| 3000")]
    assert len(rows) == 2
    for row in rows:
        assert row[3] == "10/10" and float(row[4]) < 0.02 and float(row[5]) == 0.0
        assert row[6].startswith("PURE_ROTATION")
        assert abs(float(row[7].split()[0]) / 1380.0 - 1) < 2e-3
    assert "z = 3: 0" in out


def test_probe_survey_on_a_small_flat_field(capsys):
    """Ten nadir views over flat ground, the camera known: every view, the camera kept as given
    (the focal the flat field cannot fix is not taken), a rotation error of a known camera."""
    probe_survey = load_script("probe_survey")
    assert probe_survey.main(["--seeds", "1", "--strips", "2", "--per-strip", "5", "--relief", "0",
                              "--points", "8000", "--focal-factors"]) == 0
    (row,) = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| 0 ")]
    assert row[3:5] == ["rotonly", "10/10"] and float(row[5]) < 0.03 and float(row[6]) < 0.05
    assert row[7].startswith("1380.0") and row[8] == "kept"


def test_scaled_camera_follows_the_resize():
    """A 2x shrink halves every PINHOLE parameter in COLMAP's corner-at-0 convention; a shrink
    that rounds the height scales each axis by its own ratio."""
    probe_lowres = load_script("probe_low_resolution")
    np.testing.assert_allclose(probe_lowres.scaled_camera([1380.0, 1382.0, 768.0, 512.0], (1536, 1024), (768, 512)),
                               [690.0, 691.0, 384.0, 256.0])
    np.testing.assert_allclose(probe_lowres.scaled_camera([1380.0, 1380.0, 768.0, 512.0], (1536, 1024), (512, 341)),
                               [460.0, 1380.0 * 341 / 1024, 256.0, 512.0 * 341 / 1024])


def test_probe_low_resolution_on_rendered_images(tmp_path, capsys, monkeypatch):
    """Eight rendered images of a textured room (tests/test_chains.py) as a Strecha scene:
    described and matched by pycolmap at their size and at half of it, every view registered
    with a small rotation error in both rows, the images and databases kept in --work."""
    monkeypatch.syspath_prepend(str(ROOT / "tests"))  # test_chains' own helpers
    chains = load_script_at(ROOT / "tests" / "test_chains.py", "chains")
    scene = tmp_path / "root" / "Room"
    poses = chains.render(scene / "images")
    (scene / "gt_dense_cameras").mkdir()
    K = np.array([[chains.FOCAL, 0, chains.CX], [0, chains.FOCAL, chains.CY], [0, 0, 1]])  # Strecha's convention
    for index, (R, centre) in enumerate(poses):
        rows = [*K, np.zeros(3), *R.T, centre]
        text = "\n".join(" ".join(f"{v:.12g}" for v in row) for row in rows)
        (scene / "gt_dense_cameras" / f"{index:04d}.jpg.camera").write_text(f"{text}\n{chains.WIDTH} {chains.HEIGHT}\n")
    probe_lowres = load_script("probe_low_resolution")
    assert probe_lowres.main(["--root", str(tmp_path / "root"), "--scenes", "Room", "--factors", "1", "2",
                              "--mapper", "--work", str(tmp_path / "work")]) == 0
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| Room")]
    assert [row[1:3] for row in rows] == [["1", "480 x 360"], ["2", "240 x 180"]]
    for row in rows:
        assert int(row[3]) > 1000 and row[4] == "8 / 8" and float(row[5]) < 0.5 and float(row[7]) < 0.05
        assert row[9].endswith("(8 / 8)")
    assert (tmp_path / "work" / "Room_x2" / "database.db").is_file()
    assert sorted(p.name for p in (tmp_path / "work" / "Room_x2" / "images").iterdir()) == \
        [f"{index:04d}.jpg" for index in range(8)]


def test_probe_zoom_on_fixture(tmp_path, capsys):
    """The Herz-Jesu fixture's database with every third image (0000, 0005, 0007) at 5 % more
    focal under its one camera: the zoom check finds exactly those, writes two cameras and
    warns, and the rotations are those of a calibrated capture (the fixture's 0.0193 deg,
    within 2x), where the one camera as given ends 10x worse or more; the fixture is untouched."""
    from rotonly_cli.io.colmap import read_database

    probe_zoom = load_script("probe_zoom")
    scene = read_database(FIXTURES / "herzjesu_p8" / "database.db")
    views = probe_zoom.zoomed_views(scene, 3)
    zoomed = read_database(probe_zoom.zoomed_database(scene, views, 1.05, tmp_path / "zoomed.db"))
    centre = np.array([760.595, 503.655])
    for v in scene.views:
        expected = centre + (1.05 if v in views else 1.0) * (scene.keypoints[v] - centre)
        assert np.allclose(zoomed.keypoints[v], expected, atol=1e-3)
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "Herz-Jesus-P8").symlink_to(FIXTURES / "herzjesu_p8")
    before = digest(FIXTURES / "herzjesu_p8" / "database.db")
    assert probe_zoom.main(["--root", str(tmp_path / "root"), "--scenes", "Herz-Jesus-P8", "--zooms", "1.05"]) == 0
    assert digest(FIXTURES / "herzjesu_p8" / "database.db") == before
    (row,) = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| Herz")]
    assert row[2] == row[5] == "0000 0005 0007" and row[4] == "2" and row[6] == "yes"
    assert float(row[3]) < 2 * 0.0193 and float(row[7].rstrip(" |")) > 10 * float(row[3])


def test_probe_openmvg_preset_commands():
    """The probe builds a project with OpenMVG's own five tools from the images, the shared
    project's camera and the preset asked for (the run itself needs OpenMVG: not here)."""
    probe = load_script("probe_openmvg_preset")
    K = probe.shared_K(FIXTURES / "castle_p19_openmvg")
    f, _, cx, _, fy, cy, *_ = map(float, K.split(";"))
    assert f == fy and 1000 < f < 2000 and 0 < cx < 3072 and 0 < cy < 2048
    commands = probe.project_commands(Path("/bin/mvg"), Path("/data/images"), Path("/work/p"), K, "NORMAL")
    assert [Path(c[0]).name for c in commands] == [f"openMVG_main_{name}" for name in (
        "SfMInit_ImageListing", "ComputeFeatures", "PairGenerator", "ComputeMatches", "GeometricFilter")]
    assert commands[1][-2:] == ["-p", "NORMAL"] and commands[-1][commands[-1].index("-g") + 1] == "e"
    assert commands[-1][-1] == "/work/p/matches.e.bin"


def test_probe_openmvg_preset_builds_each_step_once(tmp_path):
    """build_project runs OpenMVG's steps in order, the F filter after the E one when asked,
    and on a kept project only the steps whose product is missing (fake tools here)."""
    probe = load_script("probe_openmvg_preset")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name in ("SfMInit_ImageListing", "ComputeFeatures", "PairGenerator", "ComputeMatches", "GeometricFilter"):
        tool = bin_dir / f"openMVG_main_{name}"
        product = {"SfMInit_ImageListing": '"$out/sfm_data.json"',
                   "ComputeFeatures": '"$out/image_describer.json"'}.get(name, '"$out"')
        tool.write_text(f'#!/bin/sh\nwhile [ "$1" != "-o" ]; do shift; done; out="$2"\n'
                        f'echo {name} >> "{tmp_path}/calls"\ntouch {product}\n')
        tool.chmod(0o755)
    project = tmp_path / "castle-NORMAL"
    probe.build_project(bin_dir, FIXTURES / "castle_p19_openmvg", project, "NORMAL", ["e", "f"])
    calls = (tmp_path / "calls").read_text().split()
    assert calls == ["SfMInit_ImageListing", "ComputeFeatures", "PairGenerator", "ComputeMatches",
                     "GeometricFilter", "GeometricFilter"]
    assert (project / "matches.e.bin").is_file() and (project / "matches.f.bin").is_file()
    (project / "matches.f.bin").unlink()
    probe.build_project(bin_dir, FIXTURES / "castle_p19_openmvg", project, "NORMAL", ["e", "f"])
    assert (tmp_path / "calls").read_text().split()[len(calls):] == ["GeometricFilter"]


def test_probe_long_tracks_completes_the_pairs_tracks_share():
    """with_track_edges adds one REGULAR edge per unmatched view pair sharing at least
    min_shared tracks (their keypoints as its matches, its rotation from the run's rotations),
    and leaves the run's own graph as it was."""
    from types import SimpleNamespace

    from rotonly_cli.scene.types import View
    from rotonly_cli.scene.view_graph import ViewGraph

    probe = load_script("probe_long_tracks")
    rng = np.random.default_rng(3)
    R = so3.exp(rng.normal(scale=0.1, size=(3, 3)))
    m = np.arange(40)
    def edge(i, j, a, b):
        return Edge(i=i, j=j, R_j_from_i=R[j] @ R[i].T, t_dir=np.array([1.0, 0, 0]),
                    matches=np.stack([a, b], axis=1), scene_kind="REGULAR")

    # keypoint k of view 0 <-> k + 5 of view 1 <-> k + 9 of view 2, pairs (0, 1) and (1, 2) matched
    graph = ViewGraph(views={v: View(id=v, name=f"{v}.png", intrinsics_id=0) for v in range(3)},
                      edges=[edge(0, 1, m, m + 5), edge(1, 2, m + 5, m + 9)])
    run = SimpleNamespace(graph=graph, rotations=R)
    completed, added, matched = probe.with_track_edges(run, min_shared=30)
    assert (added, matched, len(graph.edges)) == (1, 80, 2)
    new = completed.graph.edges[-1]
    assert (new.i, new.j, new.scene_kind) == (0, 2, "REGULAR")
    assert np.array_equal(np.sort(new.matches, axis=0), np.stack([m, m + 9], axis=1))
    assert np.allclose(new.R_j_from_i, R[2] @ R[0].T)
    assert probe.with_track_edges(run, min_shared=41)[1] == 0
