"""LiGT: linear global translation from known rotations and tracks (Cai et al., TPAMI 2023).

Pure numpy/scipy, the paper/OpenMVG form of algorithms.md §1.1–1.2, batched over all
tracks. Conventions: ``R_i = R_cam_from_world``, ``t_i`` = camera **centre**; normalized
observations ``x = (x, y, 1)``.

Per track k with views V_k:

* base views ``(l, r) = argmax_{a<b} ‖θ_ab‖``, ``θ_lr = [x_r]_× R_lr x_l`` (TPAMI eq. 29;
  OpenMVG ``SelectBaseViews`` scans a < b in track order and keeps the first maximum).
  ``‖θ_ab‖ = ‖(R_bᵀ x_b) × (R_aᵀ x_a)‖`` so it is computed on world rays.
* ``a_lrᵀ = ([R_lr x_l]_× x_r)ᵀ [x_r]_×``.
* for every other view i ≠ l (i = r included): ``B t_r + C t_i + D t_l = 0`` with
  ``B = [x_i]_× R_li x_l a_lrᵀ R_r``, ``C = ‖θ_lr‖² [x_i]_× R_i``, ``D = −(B + C)``.

``LᵀL`` (3n × 3n) is accumulated chunk by chunk from the constraints' 3 × 9 blocks
``M = [B | C | D]``: each ``MᵀM`` is a few outer products of 3-vectors, summed per view triple
(r, i, l) and then per 3 × 3 block of LᵀL (L itself is never formed). Gauge: the centroid of the
solved centres is 0 and their norm 1, i.e. the eigenvector of the smallest eigenvalue of LᵀL
orthogonal to the three common translations (its null space; dense ``eigh`` for small
problems, shift-invert ``eigsh`` with those translations projected out otherwise). OpenMVG and
pyTheia fix one view's centre at 0 instead; under a unit norm that favours configurations far
from that view, and a weakly linked gauge view then keeps its distance while every other centre
shrinks around one point (algorithms.md §1.2). Only the largest **rigid** set of views is
solved (:func:`rigid_views`): views whose distance to the others no track of three or more
views fixes get no centre. Sign: chirality vote ``a_lrᵀ R_r (t_l − t_r) > 0``
per track (TPAMI "Step 5", OpenMVG ``IdentifySign``).

**Output scale**: centres are returned translated so the centroid of the solved centres is
0 and scaled so their mean distance to that centroid is 1.
"""

from rotonly_cli.geometry.ligt.baselines import baseline_disagreement_deg, views_off_their_baselines
from rotonly_cli.geometry.ligt.linear import LiGTOptions, LiGTResult, ligt_normal_matrix, ligt_translations
from rotonly_cli.geometry.ligt.rigid import rigid_views
from rotonly_cli.geometry.ligt.robust import (
    RobustLiGTResult,
    observation_errors,
    outlier_threshold_px,
    robust_ligt_translations,
)

__all__ = ["LiGTOptions", "LiGTResult", "RobustLiGTResult", "baseline_disagreement_deg", "ligt_normal_matrix",
           "ligt_translations", "observation_errors", "outlier_threshold_px", "rigid_views",
           "robust_ligt_translations", "views_off_their_baselines"]
