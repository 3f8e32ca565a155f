"""Rebuild the OpenMVG fixtures from /work/shared/data/strecha/Herz-Jesus-P8/openmvg (by hand,
never from tests): python data_fixtures/openmvg_real/make_fixtures.py"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from rotonly_cli.io import openmvg

SOURCE = Path("/work/shared/data/strecha/Herz-Jesus-P8/openmvg")
HERE = Path(__file__).resolve().parent
MATCHES_KEPT_PER_PAIR = 12


def main() -> None:
    # Real OpenMVG-written files, copied byte for byte.
    shutil.copy(SOURCE / "sfm_data.json", HERE / "sfm_data.json")
    shutil.copy(SOURCE / "global" / "sfm_data.json", HERE / "global_sfm_data.json")
    shutil.copy(SOURCE / "matches.e.bin", HERE / "matches.e.bin")
    shutil.copy(SOURCE / "image_describer.json", HERE / "image_describer.json")

    # Cut-down project: per view only the features used by the first matches of each pair,
    # the original .feat lines kept verbatim (in file order) and the matches re-indexed.
    project = HERE / "cut_project"
    project.mkdir(exist_ok=True)
    shutil.copy(SOURCE / "sfm_data.json", project / "sfm_data.json")
    shutil.copy(SOURCE / "image_describer.json", project / "image_describer.json")
    matches = openmvg.read_matches(SOURCE / "matches.e.bin")
    putative = openmvg.read_matches(SOURCE / "matches.putative.bin")
    kept: dict[int, set[int]] = {}
    for (i, j), pair in matches.items():
        kept.setdefault(i, set()).update(pair[:MATCHES_KEPT_PER_PAIR, 0].tolist())
        kept.setdefault(j, set()).update(pair[:MATCHES_KEPT_PER_PAIR, 1].tolist())
    new_index = {}
    for view_id in range(8):
        lines = (SOURCE / f"{view_id:04d}.feat").read_text().splitlines(keepends=True)
        old = sorted(kept.get(view_id, set()))
        (project / f"{view_id:04d}.feat").write_text("".join(lines[k] for k in old))
        lookup = np.full(len(lines), -1)
        lookup[old] = np.arange(len(old))
        new_index[view_id] = lookup

    def restrict(all_matches):
        out = {}
        for (i, j), pair in all_matches.items():
            remapped = np.stack([new_index[i][pair[:, 0]], new_index[j][pair[:, 1]]], axis=1)
            remapped = remapped[(remapped >= 0).all(axis=1)]
            if len(remapped):
                out[(i, j)] = remapped
        return out

    openmvg.write_matches(project / "matches.e.bin", restrict(matches))
    openmvg.write_matches(project / "matches.putative.txt", restrict(putative))


if __name__ == "__main__":
    main()
