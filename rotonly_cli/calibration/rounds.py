"""The calibration of one ``rotonly run`` (calibration/, step 5): :class:`Calibration` holds
the intrinsics as given and as they evolve, takes each round's estimate
(calibration.adjustment), and writes reports/intrinsics.json; chain/calibrate.py runs the
passes of rotonly's stages around it."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from rotonly_cli.calibration.adjustment import (
    change_sigmas,
    describe,
    estimate_intrinsics,
    gate,
    half_diagonal,
    shift_limit_px,
    shift_px,
)
from rotonly_cli.calibration.focals import (
    per_image_focals,
    refit_fundamentals,
    rotating_camera_focals,
    view_graph_focals,
    zoom_warning,
)
from rotonly_cli.calibration.guesses import (
    cameras_to_calibrate,
    centred_principal_point,
    mean_reprojection_errors,
    suspect_cameras,
    suspect_threshold_px,
    twin_cameras,
)
from rotonly_cli.calibration.loose import loose_focals, loose_warning
from rotonly_cli.calibration.noise import projective_noise_sigma_px
from rotonly_cli.errors import InputError
from rotonly_cli.io import cameras
from rotonly_cli.options import Intrinsics as Mode
from rotonly_cli.options import IntrinsicsOptions
from rotonly_cli.scene.types import Intrinsics, SfMScene

logger = logging.getLogger(__name__)

def warnings_for(given: dict[int, Intrinsics], final: dict[int, Intrinsics], calibrated: set[int],
                 reprojection_px: float | None, options: IntrinsicsOptions) -> list[str]:
    """One line each: final mean reprojection error above ``warn_reprojection_px``; a camera
    not marked as a guess whose focal moved by more than ``warn_focal_change``."""
    warnings = []
    if reprojection_px is not None and reprojection_px > options.warn_reprojection_px:
        warnings.append(f"mean reprojection error {reprojection_px:.2f} px (> {options.warn_reprojection_px:g} px): "
                        f"the reconstruction does not fit the matches (intrinsics that --intrinsics {options.mode} "
                        f"did not put right, or poses bent by wrong matches)")
    for camera_id in sorted(final):
        if camera_id in calibrated and given[camera_id].prior_focal is False:
            continue  # a guess, expected to move
        change = final[camera_id].focal_px / given[camera_id].focal_px - 1.0
        if abs(change) > options.warn_focal_change:
            warnings.append(f"camera {camera_id}: focal moved {100 * change:+.1f} % from the given "
                            f"{given[camera_id].focal_px:.1f} px to {final[camera_id].focal_px:.1f} px")
    return warnings



# ============================================================================ the calibration of a run

def with_intrinsics(scene: SfMScene, changed: dict[int, Intrinsics]) -> SfMScene:
    """A copy of ``scene`` (sharing what does not change) with ``changed`` intrinsics and the
    keypoints of their views normalized again."""
    copy = replace(scene, intrinsics=dict(scene.intrinsics), normalized=dict(scene.normalized))
    cameras.renormalize(copy, changed)
    return copy


def with_focal(intrinsics: Intrinsics, focal_px: float, **changes) -> Intrinsics:
    """``intrinsics`` with its mean focal length (Intrinsics.focal_px) at ``focal_px``, the
    ratio of fx to fy kept, and ``changes`` (dataclass fields) applied."""
    params = np.array(intrinsics.params, dtype=np.float64)
    params[cameras.parameter_groups(intrinsics)["focal"]] *= focal_px / intrinsics.focal_px
    return replace(intrinsics, params=params, **changes)


def same_intrinsics(a: Intrinsics, b: Intrinsics) -> bool:
    """Whether ``a`` and ``b`` are the same camera model with the same parameters."""
    return a.model == b.model and np.array_equal(np.asarray(a.params), np.asarray(b.params))


@dataclass
class CalibrationSteps:
    """What each step of a run's calibration reported, as reports/intrinsics.json lists them."""

    #: each view-graph calibration (focals.view_graph_focals, rotating_camera_focals)
    view_graph: list[dict] = field(default_factory=list)
    #: each round's estimate (:meth:`Calibration.estimate`); the rounds' ranking reads them
    rounds: list[dict] = field(default_factory=list)
    #: per camera, the reprojection sigma of the first reconstruction that judged it
    first_reprojection_px: dict[int, float] = field(default_factory=dict)
    suspect_threshold_px: float | None = None  #: the sigma above which a camera was a suspect
    centred_check: dict | None = None  #: :meth:`Calibration.check_centred` (None: no camera checked)
    suspect_check: dict | None = None  #: the adjustment that confirms suspects (None: none to confirm)
    zoom_check: dict | None = None  #: :meth:`Calibration.check_zoom` (None: not made; it is made once)
    unsettled: dict | None = None  #: :meth:`Calibration.take_best_round` (None: the rounds settled)
    #: the calibrated reconstruction against the given intrinsics' (chain/calibrate.py
    #: no_worse_than_given; None: not compared)
    given_check: dict | None = None


@dataclass
class Calibration:
    """The intrinsics of one ``rotonly run``: as given, as they evolve, and the steps' reports.
    ``options`` and ``jobs`` are fixed; ``given`` is the input's cameras, to which a zoom check
    adds the cameras it splits off; ``scene`` is the input scene with the current intrinsics (a
    new copy at every change, so runs made with earlier intrinsics keep theirs)."""

    options: IntrinsicsOptions
    given: dict[int, Intrinsics]
    scene: SfMScene
    jobs: int = 1  #: processes for the fundamental-matrix fits
    #: cameras being calibrated, and why: "guess" (the input says so), "suspect" (its
    #: reprojection error), "refine" (--intrinsics refine), "centred principal point", "zoom"
    calibrate: dict[int, str] = field(default_factory=dict)
    #: per calibrated camera, what the estimates are compared with (refinement-model terms):
    #: the view-graph calibration's result for a guess, else the given intrinsics
    reference: dict[int, Intrinsics] = field(default_factory=dict)
    #: cameras this calibration added for images at another zoom (:meth:`_split`): {new
    #: camera: {"from": camera, "views": [...], "names": [...], "focal_px": its view-graph focal}}
    splits: dict[int, dict] = field(default_factory=dict)
    #: cameras one adjustment (:meth:`_one_adjustment`) has looked at already
    adjusted_once: set = field(default_factory=set)
    #: guesses whose focal length the matches cannot determine (calibration/loose.py): the
    #: ones that share their twins' focal, and the ones kept as given (not calibrated)
    shared_focal: set = field(default_factory=set)
    held_focal: set = field(default_factory=set)
    noise_sigma_px: float | None = None  #: the matches' noise (F-based), when it was measured
    settled: bool | None = None  #: whether the last round moved the intrinsics by little (None: no round)
    #: per round (``steps.rounds``), the scene with that round's estimate
    round_scenes: list = field(default_factory=list)
    #: wall time the calibration added to the run (view-graph focals, estimation passes and
    #: rounds; not the pass whose result is written)
    time_s: float = 0.0
    steps: CalibrationSteps = field(default_factory=CalibrationSteps)

    def shift_limit_px(self, camera_id: int) -> float:
        """:func:`shift_limit_px` of a given camera at the matches' measured noise."""
        return shift_limit_px(self.given[camera_id], self.options, self.noise_sigma_px)

    def _calibrate_focals(self, cameras_: dict[int, str]) -> None:
        focals, report = view_graph_focals(self.scene, set(cameras_), self.options, self.jobs)
        self.steps.view_graph.append(report)
        shared, held = loose_focals(self.given, self.scene, report["fundamental_pairs_by_camera"], self.options)
        self.shared_focal |= shared
        if set(cameras_) - set(focals):  # no fundamental matrix fixed them: a rotating camera?
            rotating, rotating_report = rotating_camera_focals(self.scene, set(cameras_) - set(focals), self.options)
            if rotating_report["cameras"]:
                self.steps.view_graph.append(rotating_report)
            focals = {**focals, **rotating}
            held -= set(rotating)
        # a focal the matches cannot determine is not calibrated: it stays as given (loose.py)
        self.held_focal |= held
        cameras_ = {c: why for c, why in cameras_.items() if c not in held}
        focals = {c: k for c, k in focals.items() if c not in held}
        self.scene = with_intrinsics(self.scene, focals)
        for camera_id, why in cameras_.items():
            self.calibrate[camera_id] = why
            # what an estimate must differ from to be kept: the view-graph calibration for a
            # focal the input calls a guess, else the intrinsics as given
            guess = self.given[camera_id].prior_focal is False
            self.reference[camera_id] = cameras.refinement_model(
                self.scene.intrinsics[camera_id] if guess else self.given[camera_id])
            if self.reference[camera_id] is None and not guess and camera_id in focals:
                # no refinement of this model: the view-graph focal is the only estimate, kept
                # if significant
                if shift_px(self.given[camera_id], focals[camera_id]) <= self.shift_limit_px(camera_id):
                    self.scene = with_intrinsics(self.scene, {camera_id: self.given[camera_id]})

    def check_zoom(self) -> bool:
        """Once, when the rounds have settled: do the images of each calibrated camera agree on
        its focal (:func:`per_image_focals`)? The check's cameras (:meth:`_check_camera`) take
        the rounds' distortion and focal, and the given principal point; images at another zoom
        get a camera of their own (:meth:`_split`). True if some did: the rounds go on.
        On the first view-graph calibration's cameras (no distortion yet), a simulated capture
        with k1 = -0.3 and the focal guessed 40 % long split its images at 2149 and 3112 px
        (true: 1380 for all); on the settled ones as they are, a zoom bends the principal
        point by tens of pixels, and the groups drown."""
        if not self.options.zoom_check or self.steps.zoom_check is not None:
            return False
        start = time.perf_counter()
        # twins are one device, checked from one camera (the rounds gave a guess's twins a focal each)
        devices = twin_cameras(self.given, {c for c in self.calibrate if c not in self.splits})
        checked = {c: replace(self._check_camera(group), id=c) for group in devices for c in group}
        scene = with_intrinsics(self.scene, checked)
        fundamentals = refit_fundamentals(scene, self.options, self.jobs) if devices else {}
        self.steps.zoom_check = per_image_focals(scene, devices, fundamentals, self.options) if fundamentals else {}
        split = [self._split(finding, checked) for finding in self.steps.zoom_check.get("disagree", [])]
        self.steps.zoom_check["time_s"] = time.perf_counter() - start
        self.time_s += self.steps.zoom_check["time_s"]
        return any(split)

    def _check_camera(self, device: list[int]) -> Intrinsics:
        """The given camera of ``device`` (twins' camera ids) with the current distortion (its
        first camera's) and mean focal length (the given ratio of fx to fy kept): what the
        zoom check calibrates each image from."""
        given, current = self.given[device[0]], self.scene.intrinsics[device[0]]
        distortion = cameras.parameter_groups(given).get("distortion", [])
        params = np.array(given.params, dtype=np.float64)
        if current.model == given.model and len(distortion):
            params[distortion] = np.asarray(current.params, dtype=np.float64)[distortion]
        return with_focal(replace(given, params=params),
                          float(np.mean([self.scene.intrinsics[c].focal_px for c in device])))

    def _split(self, finding: dict, checked: dict[int, Intrinsics]) -> bool:
        """One camera's images at two focal lengths (a :func:`per_image_focals` finding on the
        ``checked`` cameras): the group whose focal lies farther from the camera's given one
        moves to a camera of its own, both restart from the checked camera with their group's
        focal, and the new one is calibrated as a guess from there (its ``given`` says so: the
        input's focal is wrong for those images). Only a camera of its own images; twins (a
        camera per image, the images of each group still tied by one focal) keep the warning."""
        camera_id = finding["camera"]
        if any(camera_id in group and len(group) > 1 for group in twin_cameras(self.given, self.given)):
            return False
        given_focal = self.given[camera_id].focal_px
        low, high = finding["groups"]
        move = max((low, high), key=lambda group: abs(np.log(group["focal_px"] / given_focal)))
        keep = high if move is low else low
        new_id = max(set(self.given) | set(self.scene.intrinsics)) + 1
        # Not a twin of the camera it came from: twins share the first adjustment's focal,
        # which bent a simulated capture's principal point by 18 px
        self.given[new_id] = with_focal(self.given[camera_id], move["focal_px"], id=new_id, prior_focal=False)
        views = {v: replace(view, intrinsics_id=new_id) if v in move["views"] else view
                 for v, view in self.scene.views.items()}
        self.scene = with_intrinsics(replace(self.scene, views=views), {
            new_id: with_focal(checked[camera_id], move["focal_px"], id=new_id),
            camera_id: with_focal(checked[camera_id], keep["focal_px"])})
        self.calibrate[new_id] = "zoom"
        self.reference[new_id] = cameras.refinement_model(self.scene.intrinsics[new_id])
        self.splits[new_id] = {"from": camera_id, "views": list(move["views"]), "names": list(move["names"]),
                               "focal_px": float(move["focal_px"])}
        logger.info("intrinsics: camera %d's images %s are at another zoom (%.0f px against %.0f px): camera %d, "
                    "calibrated on its own", camera_id, ", ".join(move["names"]), move["focal_px"], keep["focal_px"],
                    new_id)
        return True

    def add_suspects(self, sigma_by_camera: dict[str, float], scene: SfMScene,
                     posed: Callable[[], SfMScene] | None = None) -> bool:
        """auto: cameras not yet calibrated whose reprojection errors in the first
        reconstruction (``sigma_by_camera``: robust sigma in px of every observation's error
        before triangulation drops any, the triangulate stage's report) show them wrong join
        the calibration, starting with their focal from the view graph. True if any did.
        The matches' noise (``scene``'s) is measured only if some sigma is above the floor.
        ``posed``: makes that reconstruction, whose one adjustment (:meth:`_one_adjustment`) must
        confirm a suspect: the sigma alone cannot tell a camera 2 % off from a calibrated one
        (docs/tuning.md "Intrinsics"), and a suspect the adjustment leaves where it was would
        cost a round and a pass for the same result."""
        per_camera = {int(c): float(v) for c, v in sigma_by_camera.items()}
        self.steps.first_reprojection_px = self.steps.first_reprojection_px or per_camera  # a probe's came first
        noise = None
        if any(v > self.options.suspect_reprojection_px for v in per_camera.values()):
            noise = self.noise_sigma_px = projective_noise_sigma_px(scene, self.options)
        self.steps.suspect_threshold_px = suspect_threshold_px(noise, self.options)
        suspects = suspect_cameras(per_camera, self.steps.suspect_threshold_px)
        # twins are one device as the front end left it: what shows one of them wrong shows
        # the others (whose own errors may sit just below the threshold) and they are
        # calibrated together, sharing their principal point
        suspects = {c for group in twin_cameras(self.given, self.given) if suspects & set(group) for c in group
                    if c not in self.calibrate}
        if suspects:
            sigmas = ", ".join(f"{per_camera.get(c, float('nan')):.2f}" for c in sorted(suspects))
            if posed is not None:
                confirmed, self.steps.suspect_check = self._one_adjustment(posed(), suspects)
                if not confirmed:
                    logger.info("intrinsics: camera(s) %s reproject with sigma %s px (> %.2f px), but one adjustment "
                                "moves them by less than %.1f px or within %g standard deviations of its estimate: "
                                "kept as given", sorted(suspects), sigmas, self.steps.suspect_threshold_px,
                                min(self.shift_limit_px(c) for c in suspects), self.options.min_change_sigmas)
                    return False
            logger.info("intrinsics: camera(s) %s reproject with sigma %s px (> %.2f px): calibrating them",
                        sorted(suspects), sigmas, self.steps.suspect_threshold_px)
            self._calibrate_focals(dict.fromkeys(sorted(suspects), "suspect"))
        return bool(suspects)

    def _gated_estimates(self, posed: SfMScene, camera_ids: set[int], reference: dict[int, Intrinsics],
                         guesses: frozenset[int] = frozenset()) -> tuple[dict[int, Intrinsics], dict]:
        """One :func:`estimate_intrinsics` of ``camera_ids`` on the reconstruction ``posed``
        (twins sharing), each camera's estimate gated against its ``reference`` (:func:`gate`;
        the focal of a camera in ``guesses`` always taken): {camera: intrinsics as the input's
        model}, and the report with the shifts."""
        estimated, report = estimate_intrinsics(posed, camera_ids, self.options, twin_cameras(self.given, camera_ids),
                                                frozenset(self.shared_focal))
        gated, shifts, sigmas = {}, {}, {}
        for camera_id, estimate in estimated.items():
            # a focal the input marks as a guess has no value to protect: the view-graph focal
            # is a start, and the estimate is better on average (algorithms.md §8 "Significant
            # changes only"); the other groups change when significant
            always = frozenset({"focal"}) if camera_id in guesses else frozenset()
            std = report["parameter_std"].get(str(camera_id))
            std = None if std is None else np.array(std)
            camera, shifts[camera_id] = gate(reference[camera_id], estimate, self.options, always,
                                             self.noise_sigma_px, std)
            gated[camera_id] = cameras.from_refinement_model(self.given[camera_id], camera)
            sigmas[camera_id] = change_sigmas(reference[camera_id], estimate, std)
        report["shifts_px"] = {str(c): v for c, v in shifts.items()}
        report["change_sigmas"] = {str(c): v for c, v in sigmas.items() if v is not None}
        return gated, report

    def _changes(self, before: dict[int, Intrinsics], after: dict[int, Intrinsics]) -> tuple[dict, float]:
        """The cameras of ``after`` that differ from ``before``, and the largest image shift
        that makes, as a fraction of the half diagonal."""
        changed = {c: k for c, k in after.items() if not same_intrinsics(k, before[c])}
        moved = max((shift_px(before[c], k) / half_diagonal(before[c]) for c, k in changed.items()), default=0.0)
        return changed, moved

    def _one_adjustment(self, posed: SfMScene, checked: set[int]) -> tuple[dict[int, Intrinsics], dict]:
        """The cameras of ``checked`` whose estimate from the reconstruction ``posed`` (one
        :func:`estimate_intrinsics`, twins sharing) differs significantly from the given
        intrinsics (:func:`gate`): {camera: gated intrinsics}, and the report."""
        gated, report = self._gated_estimates(posed, checked, {c: cameras.refinement_model(self.given[c])
                                                               for c in checked})
        changed, moved = self._changes(self.given, gated)
        report.update(calibrated=sorted(changed), moved=moved)
        self.time_s += report["time_s"]
        self.adjusted_once |= set(checked)
        return changed, report

    def check_centred(self, posed: Callable[[], SfMScene]) -> bool:
        """auto: cameras marked known (not yet calibrated) whose principal point sits at the
        image centre (:func:`centred_principal_point`) are checked by one estimate from the
        first reconstruction (``posed`` makes it); those it moves significantly (:func:`gate` against
        the given intrinsics) join the calibration, starting from the gated estimate. True if
        any did. The reprojection errors cannot show such a camera: an 11 px principal point
        error leaves them at calibrated cameras' level (docs/tuning.md "Intrinsics")."""
        tolerance = self.options.centred_principal_point_px
        if tolerance is None:
            return False
        checked = {c for c, k in self.given.items() if c not in self.calibrate and c not in self.adjusted_once
                   and k.prior_focal is not False
                   and cameras.refinement_model(k) is not None and centred_principal_point(k, tolerance)}
        if not checked:
            return False
        changed, report = self._one_adjustment(posed(), checked)
        for camera_id in changed:
            self.calibrate[camera_id] = "centred principal point"
            self.reference[camera_id] = cameras.refinement_model(self.given[camera_id])
        self.steps.centred_check = report
        shifts, sigmas = report["shifts_px"], report["change_sigmas"]
        logger.info("intrinsics: camera(s) %s have their principal point at the image centre (a default); "
                    "one adjustment moves them by %s px (limit %s), %s standard deviations of its estimate "
                    "(limit %g): %s", sorted(checked),
                    ", ".join(f"{max(shifts.get(str(c), {}).values(), default=0.0):.1f}" for c in sorted(checked)),
                    ", ".join(f"{self.shift_limit_px(c):.1f}" for c in sorted(checked)),
                    ", ".join(f"{max(sigmas[str(c)].values(), default=0.0):.1f}" if str(c) in sigmas else "?"
                              for c in sorted(checked)),
                    self.options.min_change_sigmas, f"calibrating {sorted(changed)}" if changed else "kept as given")
        if changed:
            self.scene = with_intrinsics(self.scene, changed)
        return bool(changed)

    def estimate(self, posed: SfMScene) -> bool:
        """One round: the intrinsics estimated from the reconstruction ``posed``, each change
        kept when significant (:func:`gate`); ``scene`` takes the new intrinsics. True when
        they moved the image by no more than ``converged_shift`` and the focal lengths by no
        more than ``converged_focal_change`` (settled)."""
        gated, report = self._gated_estimates(posed, set(self.calibrate), self.reference,
                                              frozenset(c for c, why in self.calibrate.items() if why == "guess"))
        changed, moved = self._changes(self.scene.intrinsics, gated)
        focal_change = max((abs(k.focal_px / self.scene.intrinsics[c].focal_px - 1.0) for c, k in changed.items()),
                           default=0.0)
        self.scene = with_intrinsics(self.scene, changed) if changed else self.scene
        report.update(moved=moved, focal_change=focal_change,
                      result={str(c): describe(self.scene.intrinsics[c]) for c in sorted(self.calibrate)})
        self.steps.rounds.append(report)
        self.round_scenes.append(self.scene)
        logger.info("intrinsics: round %d (%.2f s): %s", len(self.steps.rounds), report["time_s"],
                    self._calibrated_text())
        self.settled = moved <= self.options.converged_shift and focal_change <= self.options.converged_focal_change
        return self.settled

    def take_best_round(self) -> None:
        """Rounds that did not settle: the calibrated cameras take the estimate of the round
        whose adjustment converged on the most points (the least bent reconstruction keeps the
        most tracks), else of the round with the most points; the report's ``unsettled`` names
        it."""
        def rank(report: dict) -> tuple[bool, int]:
            return report.get("termination") == "CONVERGENCE", int(report.get("num_points") or 0)

        best = max(range(len(self.steps.rounds)), key=lambda k: rank(self.steps.rounds[k]))
        chosen = self.round_scenes[best]
        changed = {c: chosen.intrinsics[c] for c in self.calibrate
                   if c in chosen.intrinsics and not same_intrinsics(chosen.intrinsics[c], self.scene.intrinsics[c])}
        if changed:
            self.scene = with_intrinsics(self.scene, changed)
        self.steps.unsettled = {"taken_round": best + 1,
                          "rounds": [{"num_points": report.get("num_points"), "termination": report.get("termination")}
                                     for report in self.steps.rounds],
                          "result": {str(c): describe(self.scene.intrinsics[c]) for c in sorted(self.calibrate)}}
        converged, points = rank(self.steps.rounds[best])
        logger.info("intrinsics: the rounds did not settle; round %d's estimate, its adjustment %s on %d points, is "
                    "taken: %s", best + 1, "converged" if converged else "not converged", points,
                    self._calibrated_text())

    def _calibrated_text(self) -> str:
        """The calibrated cameras' current parameters, for the log."""
        return "; ".join(f"camera {c} {np.round(self.scene.intrinsics[c].params, 4).tolist()}"
                         for c in sorted(self.calibrate))

    def moved_from(self, scene: SfMScene) -> bool:
        """True if the current intrinsics moved the image of some camera by more than
        ``converged_shift`` from ``scene``'s (whose load stage then no longer fits)."""
        return any(c not in scene.intrinsics or shift_px(scene.intrinsics[c], self.scene.intrinsics[c])
                   / half_diagonal(scene.intrinsics[c]) > self.options.converged_shift for c in self.calibrate)

    def back_to_given(self) -> bool:
        """True when every camera is back to its given intrinsics (never after a split: a run
        with the given intrinsics gave the split images the other focal)."""
        return not self.splits and all(same_intrinsics(self.scene.intrinsics[c], k) for c, k in self.given.items())

    def given_scene(self) -> SfMScene:
        """The input scene with every camera as given."""
        return with_intrinsics(self.scene, {c: k for c, k in self.given.items()
                                            if not same_intrinsics(self.scene.intrinsics[c], k)})

    def back_to_given_after_check(self, check: dict) -> None:
        """The calibrated reconstruction reprojected worse than the given intrinsics' (``check``,
        the comparison): every camera goes back to its given intrinsics, and the run says so."""
        self.scene = self.given_scene()
        self.steps.given_check = {**check, "reverted": True}
        logger.info("intrinsics: the calibrated reconstruction reprojects at sigma %.3f px, the given intrinsics' at "
                    "%.3f px: the given intrinsics are kept", check["calibrated_sigma_px"], check["given_sigma_px"])

    def finish(self, posed: SfMScene) -> dict:
        """The report (reports/intrinsics.json) of the run's final reconstruction ``posed``."""
        per_camera, overall = mean_reprojection_errors(posed)
        final = {c: posed.intrinsics[c] for c in self.given}
        warnings = warnings_for(self.given, final, set(self.calibrate), overall, self.options)
        split_to = {split["from"]: new_id for new_id, split in self.splits.items()}
        twins = {c for group in twin_cameras(self.given, self.given) if len(group) > 1 for c in group}
        warnings += [zoom_warning(finding, split_to.get(finding["camera"]), finding["camera"] in twins)
                     for finding in (self.steps.zoom_check or {}).get("disagree", [])]
        reverted = bool((self.steps.given_check or {}).get("reverted"))
        if reverted:
            check = self.steps.given_check
            warnings.append(f"the calibration of camera(s) {', '.join(map(str, sorted(self.calibrate)))} made the "
                            f"reconstruction reproject worse than the given intrinsics (sigma "
                            f"{check['calibrated_sigma_px']:.3f} px against {check['given_sigma_px']:.3f} px): the "
                            f"given intrinsics are kept (the matches cannot determine them: a plane, too little "
                            f"parallax?); give the focal length if it is known")
        warnings += loose_warning(self.given, final, set() if reverted else self.shared_focal & set(self.calibrate),
                                  self.held_focal, self.options)
        for camera_id, intrinsic in self.given.items():
            if intrinsic.prior_focal is False and camera_id not in self.calibrate and camera_id not in self.held_focal:
                warnings.append(f"camera {camera_id}: its focal length is marked as a guess (prior_focal_length = 0) "
                                f"and is used as given (--intrinsics {self.options.mode})")
        return {
            "mode": str(self.options.mode),
            "cameras": {str(c): {"start": describe(self.given[c]), "end": describe(final[c]),
                                 "calibrated": self.calibrate.get(c), "prior_focal": self.given[c].prior_focal,
                                 "focal_change": final[c].focal_px / self.given[c].focal_px - 1.0,
                                 "reprojection_error_px": per_camera.get(c),
                                 "first_reprojection_sigma_px": self.steps.first_reprojection_px.get(c)}
                        for c in sorted(self.given)},
            "reprojection_error_px": overall, "view_graph_calibration": self.steps.view_graph,
            "rounds": self.steps.rounds,
            "settled": self.settled, "suspect_threshold_px": self.steps.suspect_threshold_px,
            "centred_principal_point_check": self.steps.centred_check, "suspect_check": self.steps.suspect_check,
            "noise_sigma_px": self.noise_sigma_px,
            "zoom_check": self.steps.zoom_check, "unsettled": self.steps.unsettled,
            "given_check": self.steps.given_check,
            "split_cameras": {str(c): split for c, split in self.splits.items()},
            "kept_given_intrinsics": all(same_intrinsics(final[c], k) for c, k in self.given.items()),
            "warnings": warnings, "time_s": self.time_s}

    def changed(self) -> dict:
        """For the workspace state: the mode and the cameras whose intrinsics differ from the
        input's ({id: {"model", "params"}}), so that the stage commands use the same."""
        cameras_ = {str(c): {"model": k.model, "params": [float(v) for v in np.asarray(k.params).ravel()]}
                    for c, k in self.scene.intrinsics.items()
                    if c in self.given and not same_intrinsics(k, self.given[c])}
        splits = {str(c): {"from": split["from"], "views": split["views"], "focal_px": split["focal_px"]}
                  for c, split in self.splits.items()}
        return {"mode": str(self.options.mode), "cameras": cameras_, **({"splits": splits} if splits else {})} \
            if cameras_ or splits else {}

    def restore(self, saved: dict) -> None:
        """The intrinsics of :meth:`changed` (saved by an earlier command) in place of the input's."""
        restored = {}
        for key, split in (saved or {}).get("splits", {}).items():  # the cameras a zoom check added
            camera_id, source = int(key), int(split["from"])
            if source not in self.given or camera_id in self.given or not set(split["views"]) <= set(self.scene.views):
                raise InputError("the workspace's split camera does not fit the input",
                                 field=f"state.npz options.intrinsics.splits[{key}]")
            self.given[camera_id] = with_focal(self.given[source], float(split["focal_px"]), id=camera_id,
                                               prior_focal=False)
            views = {v: replace(view, intrinsics_id=camera_id) if v in split["views"] else view
                     for v, view in self.scene.views.items()}
            self.scene = with_intrinsics(replace(self.scene, views=views), {camera_id: self.given[camera_id]})
            self.splits[camera_id] = {"from": source, "views": list(split["views"]),
                                      "focal_px": float(split["focal_px"])}
        for key, camera in (saved or {}).get("cameras", {}).items():
            camera_id = int(key)
            if camera_id not in self.given:
                raise InputError("the workspace's intrinsics name a camera the input does not have",
                                 field=f"state.npz options.intrinsics.cameras[{key}]")
            restored[camera_id] = replace(self.given[camera_id], model=camera["model"],
                                          params=np.asarray(camera["params"], dtype=np.float64))
            self.calibrate[camera_id] = "restored"
        if restored:
            self.scene = with_intrinsics(self.scene, restored)


def run_summary(report: dict) -> dict:
    """The run summary's part of a calibration's report (:meth:`Calibration.finish`):
    intrinsics at start and end per camera, the final mean reprojection error, the warnings."""
    return {"intrinsics": {c: {"start": v["start"]["params"], "end": v["end"]["params"],
                               "model": [v["start"]["model"], v["end"]["model"]]}
                           for c, v in report["cameras"].items()},
            "reprojection_error_px": report["reprojection_error_px"], "warnings": report["warnings"]}


def start_calibration(scene: SfMScene, options: IntrinsicsOptions, calibrate_now: bool = True,
                      jobs: int = 1) -> Calibration:
    """The calibration of a run on ``scene`` as read: the cameras to calibrate from the start
    get their focal length from the view graph (before the load stage) if ``calibrate_now``."""
    options.validate()
    calibration = Calibration(options, dict(scene.intrinsics), scene, jobs=jobs)
    calibrate = cameras_to_calibrate(scene, options.mode) if calibrate_now else set()
    if calibrate:
        why = "refine" if options.mode == Mode.REFINE else "guess"
        calibration._calibrate_focals(dict.fromkeys(sorted(calibrate), why))
    return calibration
