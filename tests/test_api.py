"""The Python entry points: ``rotonly_cli.run`` (paths, a pycolmap.Database, a
pycolmap.Reconstruction) gives `rotonly run`'s rotations bit for bit; ``multiview.average_rotations``;
the two-view and multi-view APIs refuse pixel coordinates; the README's Python examples run."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pycolmap
import pytest

import rotonly_cli
from rotonly_cli import multiview, twoview
from rotonly_cli.cli import main
from rotonly_cli.errors import InputError
from rotonly_cli.geometry import so3

from helpers import DATA_FIXTURES, REPOSITORY

INPUTS = {
    "herzjesu_db": DATA_FIXTURES / "herzjesu_p8" / "database.db",
    "herzjesu_openmvg": DATA_FIXTURES / "herzjesu_p8" / "openmvg" / "sfm_data.json",
    "fountain_db": DATA_FIXTURES / "fountain_p11" / "database.db",
    "fountain_openmvg": DATA_FIXTURES / "fountain_p11" / "openmvg" / "sfm_data.json",
    "colmap38_db": DATA_FIXTURES / "colmap38_herzjesu4" / "database.db",
}


def _cli_poses(input_path, out) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """image name -> (rotation, centre) of OUT/sfm_data.json after `rotonly run INPUT -o OUT`."""
    with pytest.raises(SystemExit) as exit_info:
        main(["-q", "run", str(input_path), "-o", str(out)])
    assert exit_info.value.code == 0
    document = json.loads((out / "sfm_data.json").read_text())
    names = {item["key"]: item["value"]["ptr_wrapper"]["data"]["filename"] for item in document["views"]}
    pose_of = {item["value"]["ptr_wrapper"]["data"]["id_pose"]: item["key"] for item in document["views"]}
    return {names[pose_of[item["key"]]]: (np.array(item["value"]["rotation"]), np.array(item["value"]["center"]))
            for item in document["extrinsics"]}


@pytest.mark.parametrize("name", sorted(INPUTS))
def test_run_reproduces_the_cli_bit_for_bit(name, tmp_path):
    shutil.copytree(INPUTS[name].parent, tmp_path / "input", dirs_exist_ok=True)
    source = tmp_path / "input" / INPUTS[name].name
    expected = _cli_poses(source, tmp_path / "cli")
    result = rotonly_cli.run(source)
    assert result.unregistered_views == [] or name == "colmap38_db"
    got = {result.view_names[v]: (R, result.centers[v]) for v, R in result.rotations.items()}
    assert got.keys() == expected.keys()
    for image, (R, c) in expected.items():
        assert np.array_equal(got[image][0], R), image  # bit for bit
        assert np.array_equal(got[image][1], c), image
    assert len(result.points) == result.summary["num_points"] > 0 and result.colors.shape == (len(result.points), 3)
    if name == "herzjesu_db":  # an open pycolmap.Database, and run(..., out=) writing the workspace
        database = pycolmap.Database.open(str(source))
        try:
            from_database = rotonly_cli.run(database)
        finally:
            database.close()
        assert all(np.array_equal(from_database.rotations[v], R) for v, R in result.rotations.items())
        written = rotonly_cli.run(source, tmp_path / "api_out")
        assert _cli_poses(source, tmp_path / "cli2").keys() == expected.keys()
        assert all(np.array_equal(written.rotations[v], R) for v, R in result.rotations.items())
        assert (tmp_path / "api_out" / "report.html").is_file()


def test_run_on_a_reconstruction_and_back():
    """A pycolmap.Reconstruction: its tracks are the matches; the result converts back."""
    first = rotonly_cli.run(INPUTS["herzjesu_db"])
    model = first.to_pycolmap()
    assert model.num_reg_images() == 8 and model.num_points3D() == len(first.points)
    again = rotonly_cli.run(model)
    assert again.unregistered_views == [] and again.reports["load"]["input_kind"] == "colmap-model"
    ids = sorted(first.rotations)
    by_name = {again.view_names[v]: v for v in again.rotations}
    R1 = np.stack([first.rotations[v] for v in ids])
    R2 = np.stack([again.rotations[by_name[first.view_names[v]]] for v in ids])
    relative = np.degrees(so3.geodesic_angle(R1[1:] @ R1[0].T, R2[1:] @ R2[0].T))
    assert relative.max() < 0.05


def test_run_options_are_the_cli_options(tmp_path):
    with pytest.raises(InputError, match="min_inliers"):
        rotonly_cli.run(INPUTS["herzjesu_db"], min_inliers=3)
    result = rotonly_cli.run(INPUTS["herzjesu_db"], reestimate="all", grrm=False, ransac_max_error=1.5,
                             max_residual_deg=4.0, jobs=1, gt=DATA_FIXTURES / "herzjesu_p8")
    assert result.reports["load"]["num_reestimated"] == result.reports["load"]["num_pairs"] - 1
    assert result.reports["load"]["ransac_max_error_px"] == 1.5
    assert result.reports["optimize"] == {"skipped": "disabled (--no-grrm)"}
    assert result.reports["average"]["max_residual_deg"] == 4.0
    assert result.evaluation["num_matched"] == 8 and result.evaluation["rotation_error_deg"]["mean"] < 0.1
    with pytest.raises(InputError):
        rotonly_cli.run(42)


def test_the_cli_and_the_api_name_the_options_alike():
    """One mapping (options.settings.SETTINGS) serves both: the keywords of rotonly_cli.run and
    the options of `rotonly run` (--no-grrm aside: the CLI passes grrm=not no_grrm) are its names."""
    import inspect

    from rotonly_cli.cli.run import command
    from rotonly_cli.options.settings import SETTINGS

    assert set(inspect.signature(rotonly_cli.run).parameters) - {"input", "out", "options"} == set(SETTINGS)
    cli = {param.name for param in command.params if param.expose_value} - {"input_path", "out_dir", "no_grrm"}
    assert cli == set(SETTINGS) - {"grrm", "progress"}


def test_average_rotations():
    rng = np.random.default_rng(3)
    truth = {v: so3.exp(rng.normal(size=3)) for v in (10, 11, 12, 13, 14)}
    relative = {(i, j): truth[j] @ truth[i].T for i in truth for j in truth if i < j}
    relative[(10, 14)] = so3.exp(np.array([0.0, 0.6, 0.0])) @ relative[(10, 14)]  # a gross outlier
    relative[(20, 21)] = np.eye(3)  # not connected to the fixed view
    result = multiview.average_rotations(relative, weights={key: 100.0 for key in relative})
    assert result.outliers == [(10, 14)] and result.unregistered == [20, 21] and result.converged
    assert np.array_equal(result.rotations[10], np.eye(3))
    for i in truth:
        for j in truth:
            if i < j:
                error = so3.geodesic_angle(result.rotations[j] @ result.rotations[i].T, truth[j] @ truth[i].T)
                assert np.degrees(error) < 0.05
    assert result.edge_residual_deg[(10, 14)] > 20
    with pytest.raises(ValueError, match="relative_rotations"):
        multiview.average_rotations({(1, 1): np.eye(3)})
    with pytest.raises(ValueError, match="relative_rotations"):
        multiview.average_rotations({(1, 2): 2 * np.eye(3)})
    with pytest.raises(ValueError, match="weights"):
        multiview.average_rotations({(1, 2): np.eye(3)}, weights={})


def _edge(rng, m=60):
    """Normalized matches of a small translation and rotation, and the same in pixels."""
    X = rng.uniform([-2, -2, 4], [2, 2, 8], size=(m, 3))
    R = so3.exp(np.array([0.02, -0.05, 0.01]))
    x_i = X[:, :2] / X[:, 2:]
    Y = X @ R.T + [0.3, 0.0, 0.0]
    x_j = Y[:, :2] / Y[:, 2:]
    return R, x_i, x_j


def test_pixels_are_refused():
    rng = np.random.default_rng(5)
    R, x_i, x_j = _edge(rng)
    K = lambda x: 800.0 * x + [640.0, 480.0]  # noqa: E731
    assert twoview.refine_rotation(R, x_i, x_j).kind == "REGULAR"  # normalized: fine
    with pytest.raises(ValueError, match=r"^x_i: these look like pixel coordinates"):
        twoview.refine_rotation(R, K(x_i), K(x_j))
    with pytest.raises(ValueError, match=r"^x_j: these look like pixel"):
        twoview.identify_scene(R, x_i, K(x_j))
    homogeneous = np.concatenate([K(x_j), np.ones((len(x_j), 1))], axis=1)
    with pytest.raises(ValueError, match=r"^x_j: .*pixel"):
        twoview.identify_scene(R, x_i, homogeneous)
    bearings = np.concatenate([x_j, np.ones((len(x_j), 1))], axis=1)
    twoview.identify_scene(R, x_i, bearings / np.linalg.norm(bearings, axis=1, keepdims=True))  # fine
    with pytest.raises(ValueError, match=r"^xs_i\[1\]: these look like pixel"):
        twoview.refine_rotations(np.stack([R, R]), [x_i, K(x_i)], [x_j, x_j])
    with pytest.raises(ValueError, match=r"observations\[1\]: these look like pixel"):
        multiview.optimize_rotations({0: np.eye(3), 1: R}, {0: x_i, 1: K(x_j)},
                                     {(0, 1): np.stack([np.arange(60), np.arange(60)], axis=1)})


def test_readme_python_examples_run(monkeypatch):
    """Every README Python block that calls rotonly_cli.run or average_rotations runs as written
    (from the repository's root, on the bundled fixture)."""
    readme = (REPOSITORY / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", readme, re.S)
              if "rotonly_cli.run(" in b or "average_rotations(" in b]
    assert len(blocks) >= 1
    monkeypatch.chdir(REPOSITORY)
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})
