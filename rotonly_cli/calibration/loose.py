"""Focal lengths the matches cannot determine (calibration/, step 1 for guesses; issue 51
item 3; docs/tuning.md "Cameras that cannot be calibrated").

A pair's epipolar geometry says something of its cameras' focal lengths only when it holds
a fundamental matrix (Kⱼᵀ F Kᵢ an essential matrix: the view-graph calibration, algorithms.md
§8) or is a pure rotation (H = Kⱼ R Kᵢ⁻¹: the rotating-camera fit). A plane seen from several
places holds neither (its pairs are PLANAR / PLANAR_OR_PANORAMIC, NO_FUNDAMENTAL): there only
a focal shared by several images is fixed (by the bundle adjustment of the rounds, as for a
single camera over flat ground), and one per image wanders (a wall seen by six images, a
camera each marked as a guess at the right 1000 px: 418-1146 px, 4.4-7.6° of rotation
error, against 0.012-0.06° with the focal held). So a guessed camera whose images hold
fewer than ``zoom_min_pairs`` fundamental matrices

* shares its focal length with its twins (the cameras given the same guess: COLMAP's camera
  per image), estimated as one camera over all their images;
* keeps the given focal when it has no twins, one image and no fundamental matrix at all,
  unless its pairs fit pure rotations (the rotating-camera fit calibrated it).
"""

from __future__ import annotations

from collections import Counter

from rotonly_cli.calibration.guesses import twin_cameras
from rotonly_cli.options import IntrinsicsOptions
from rotonly_cli.scene.types import Intrinsics, SfMScene


def loose_focals(given: dict[int, Intrinsics], scene: SfMScene, fundamental_pairs: dict[str, int],
                 options: IntrinsicsOptions) -> tuple[set[int], set[int]]:
    """(shared, held) among the cameras of ``fundamental_pairs`` ({camera: pairs of its views
    holding a fundamental matrix}, the view-graph calibration's report): the guesses whose
    focal is their twins' one, and the guesses whose focal stays as given (module docstring).
    ``scene``: whose views say how many images each camera has."""
    counts = {int(c): n for c, n in fundamental_pairs.items()}
    loose = {c for c, n in counts.items() if n < options.zoom_min_pairs and given[c].prior_focal is False}
    images = Counter(view.intrinsics_id for view in scene.views.values())
    shared, held = set(), set()
    for group in twin_cameras(given, set(given)):
        on_group = set(group) & loose
        if len(group) > 1:
            shared |= on_group
        else:
            held |= {c for c in on_group if counts[c] == 0 and images[c] < 2}
    return shared, held


def _listed(camera_ids) -> str:
    ids = sorted(camera_ids)
    return ", ".join(map(str, ids[:8])) + (f" and {len(ids) - 8} more" if len(ids) > 8 else "")


def loose_warning(given: dict[int, Intrinsics], final: dict[int, Intrinsics], shared: set[int],
                  held: set[int], options: IntrinsicsOptions) -> list[str]:
    """One line for the cameras of ``shared`` and ``held`` (none without them): what their
    focal lengths are now and why."""
    if not shared and not held:
        return []
    parts = []
    if shared:
        focals = sorted({round(final[c].focal_px, 1) for c in shared})
        parts.append(f"camera(s) {_listed(shared)} share one focal length with the cameras given the same guess "
                     f"({', '.join(f'{f:g}' for f in focals)} px)")
    if held:
        parts.append(f"camera(s) {_listed(held)} keep the given focal length "
                     f"({', '.join(f'{given[c].focal_px:g}' for c in sorted(held)[:8])} px)")
    return [f"{'; '.join(parts)}: their focal lengths are marked as guesses, but their images hold fewer than "
            f"{options.zoom_min_pairs} fundamental matrices each (a plane, pure rotations or too little parallax), "
            f"which cannot determine a focal length per image; give the focal length if it is known"]
