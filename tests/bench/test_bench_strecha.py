"""``rotonly bench strecha``: every row of both tables computed on the pairs ``rotonly run`` keeps
before GRRM, the table header stating them, and ``rotonly run`` as a row (issue 51 item 4)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rotonly_cli.cli import cli

from helpers import DATA_FIXTURES


def _numbers(cell: str) -> list[float]:
    return [float(v) for v in re.findall(r"\d+\.\d+(?:e-?\d+)?", cell)]


class _GRRMWitness:
    """Wraps the chain's optimize stage: the active edges (i, j) of the graph each GRRM of the
    chain is given (the reject stage's re-solves call the stage function directly, not this)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        from rotonly_cli import chain

        self.calls: list[list[tuple[str, str]]] = []
        real = chain.STAGE_FUNCTIONS["optimize"]

        def optimize(run) -> None:
            names = {v: view.name for v, view in run.scene.views.items()}
            self.calls.append(sorted((names[run.graph.edges[k].i], names[run.graph.edges[k].j])
                                     for k in run.graph.active_edges()))
            real(run)

        monkeypatch.setitem(chain.STAGE_FUNCTIONS, "optimize", optimize)


def test_kept_pairs_are_those_grrm_gets(monkeypatch: pytest.MonkeyPatch) -> None:
    """On the Herz-Jesus-P8 fixture's database (28 pairs, 2 with too few inliers): the kept pairs
    are exactly the edges `rotonly run` hands GRRM, with the load stage's relative poses as the
    start, and the run's own rotations come along."""
    from rotonly_cli.bench.strecha_pairs import kept_pairs
    from rotonly_cli.geometry import so3
    from rotonly_cli.io.colmap import read_database
    from rotonly_cli.options import RunOptions

    witness = _GRRMWitness(monkeypatch)
    database = DATA_FIXTURES / "herzjesu_p8" / "database.db"
    front = kept_pairs(database, RunOptions(progress=False, jobs=1))
    assert len(witness.calls) == 1
    named = sorted((front.names[i], front.names[j]) for i, j in front.keys)
    assert named == witness.calls[0]
    assert (len(front.keys), front.num_input_pairs, front.filtered) == (26, 28, {"too few inliers": 2})
    assert front.R_init.shape == (26, 3, 3) and front.t_init.shape == (26, 3)
    np.testing.assert_allclose(np.linalg.norm(front.t_init, axis=1), 1.0, atol=1e-9)
    scene = read_database(database)
    for k, (i, j) in enumerate(front.keys):  # the matches are the run's inliers, a subset of the input's
        given = {tuple(m) for m in scene.pairs[(i, j)].matches.tolist()}
        assert {tuple(m) for m in front.matches[k].tolist()} <= given
        np.testing.assert_array_equal(front.x_i[k], scene.normalized[i][front.matches[k][:, 0]])
        np.testing.assert_array_equal(front.x_j[k], scene.normalized[j][front.matches[k][:, 1]])
    assert 17_000 < sum(len(m) for m in front.matches) < 18_500  # 17748 at seed 0 (RANSAC inliers)
    # the run's rotations (all 8 views) agree with the initial relative poses to a fraction of a degree
    index = {v: n for n, v in enumerate(front.view_ids)}
    R = front.run_rotations
    assert np.all(np.isfinite(R))
    rel = np.stack([R[index[j]] @ R[index[i]].T for i, j in front.keys])
    assert np.degrees(so3.geodesic_angle(rel, front.R_init)).max() < 0.5


def test_bench_strecha_rows_share_the_stated_pairs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`rotonly bench strecha --quick` on the two fixture scenes: the header states the pairs
    (how many of how many), Chatterjee/ROBA/GRRM, the mapper's database and every two-view row
    use exactly the pairs the run handed its GRRM, and `rotonly run` is a row."""
    from rotonly_cli.baselines import references
    from rotonly_cli.bench import paper_multiview

    witness = _GRRMWitness(monkeypatch)
    global_pairs: list[int] = []
    real_global = paper_multiview.global_methods

    def global_methods(num_views, edge_views, batch, obs_ids, R_rel, counts, methods):
        global_pairs.append(len(edge_views))
        assert len(R_rel) == len(counts) == len(edge_views) and int(counts.sum()) == len(obs_ids)
        return real_global(num_views, edge_views, batch, obs_ids, R_rel, counts, methods=methods)

    mapper_pairs: list[list[tuple[str, str]]] = []
    real_write = references._write_pairs

    def write_pairs(pycolmap, database_path, pairs):
        real_write(pycolmap, database_path, pairs)
        database = pycolmap.Database.open(str(database_path))  # what the mapper reads
        names = {image.image_id: image.name for image in database.read_all_images()}
        pair_ids, geometries = database.read_two_view_geometries()
        written = []
        for pair_id, geometry in zip(pair_ids, geometries):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            written.append((names[a], names[b]))
            assert geometry.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            np.testing.assert_array_equal(geometry.inlier_matches, pairs[(names[a], names[b])][2])
        database.close()
        mapper_pairs.append(sorted(written))

    monkeypatch.setattr(paper_multiview, "global_methods", global_methods)
    monkeypatch.setattr(references, "_write_pairs", write_pairs)
    out = tmp_path / "st"
    result = CliRunner().invoke(cli, ["bench", "strecha", "--quick", "--no-progress", "--root", str(DATA_FIXTURES),
                                      "-o", str(out)], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    text = result.output
    assert {"table.md", "results.json", "strecha.png"} <= {p.name for p in out.iterdir()}
    assert (out / "table.md").read_text() in text + "\n"
    payload = json.loads((out / "results.json").read_text())
    rows = payload["rows"]
    assert [r["scene"] for r in rows] == ["fountain_p11", "herzjesu_p8"]
    assert len(witness.calls) == len(global_pairs) == len(mapper_pairs) == 2

    assert "Pairs: those `rotonly run` keeps before GRRM, the same for every row of both tables" in text
    assert "limited to 12 verified pairs" in text
    for row, grrm_pairs, mapped in zip(rows, witness.calls, mapper_pairs):
        # the pairs of every row are the ones the run handed GRRM
        assert sorted(map(tuple, row["keys"])) == grrm_pairs == mapped
        assert row["pairs"] == len(grrm_pairs) == 12 and row["input_pairs"] == 12
        assert f"{row['scene']} ({row['pairs']} of {row['input_pairs']} pairs)" in text
        assert f"| {row['scene']} | {row['pairs']} | {row['input_pairs']} | none | {row['matches']} |" in text
        for m, s in row["twoview"].items():
            assert s["count"] == row["pairs"], m
        assert set(row["global_"]) == {"Chatterjee", "ROBA", "GRRM", "pycolmap global mapper", "rotonly run"}
        for m, s in row["global_"].items():
            assert s["count"] == row["views"], m
        assert row["global_"]["GRRM"]["mean"] < 0.05
        assert row["global_"]["rotonly run"]["mean"] < 0.05
        assert row["global_"]["GRRM"]["mean"] <= row["global_"]["Chatterjee"]["mean"] + 1e-6
        assert row["twoview"]["TRRM"]["mean"] < row["twoview"]["initial"]["mean"]
    assert global_pairs == [12, 12]
    for method in ("initial", "BA", "PA", "Kneip eigen", "Kneip nonlinear", "TRRM",
                   "Chatterjee", "ROBA", "GRRM", "pycolmap global mapper", "rotonly run"):
        line = next(line for line in text.splitlines() if line.startswith(f"| {method} |"))
        assert len(_numbers(line)) >= 2, line
    # the paper's published numbers appear next to ours: fountain-P11 TRRM 0.0561, GRRM 0.0262
    assert "(0.0561)" in text and "(0.0262)" in text


def test_bench_strecha_method_subset(tmp_path: Path) -> None:
    """--methods runs only the chosen two-view methods (the initial poses always), on the same
    pairs, with the same Table 2; an unknown method is a usage error that writes nothing."""
    args = ["bench", "strecha", "--no-progress", "--no-mapper", "--max-pairs", "6",
            "--root", str(DATA_FIXTURES / "herzjesu_p8")]
    result = CliRunner().invoke(cli, args + ["--methods", "TRRM", "-o", str(tmp_path / "sub")],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.output
    row = json.loads((tmp_path / "sub" / "results.json").read_text())["rows"][0]
    assert set(row["twoview"]) == {"initial", "TRRM"} and row["pairs"] == 6
    assert row["twoview"]["TRRM"]["count"] == 6 and row["twoview"]["TRRM"]["mean"] < 0.1
    assert set(row["global_"]) == {"Chatterjee", "ROBA", "GRRM", "rotonly run"}
    # 6 neighbouring pairs reach 7 of the 8 views: the rows say so
    assert row["views"] == 8 and row["global_"]["GRRM"]["count"] == 7 and row["global_"]["GRRM"]["mean"] < 0.1
    table = (tmp_path / "sub" / "table.md").read_text()
    assert "| TRRM |" in table and "| BA |" not in table and "herzjesu_p8 (6 of 6 pairs)" in table
    assert "[7/8 views]" in next(line for line in table.splitlines() if line.startswith("| GRRM |"))
    bad = CliRunner().invoke(cli, args + ["--methods", "TRRM,bundle", "-o", str(tmp_path / "bad")])
    assert bad.exit_code == 2 and "unknown method" in bad.output
    assert not (tmp_path / "bad").exists()
