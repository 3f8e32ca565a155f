"""GRRM: global reprojection residuals on the rotation manifold (paper Alg. 3-4).

For an observation of point k in view i (eq:GRRMRes1, eq:GRRMRes2):

    V_ik = Σ_{e_ij ∈ E_ik} ω_ijk V^{TRRM,i}_{ijk}(R_ij),    ω_ijk = ‖θ_ijk‖ / Σ_j ‖θ_ijk‖   (eq:weight)

i.e. the ‖θ‖-weighted mean of the two-view TRRM residuals that every edge through view i
that matched this observation predicts for it (bearing form, expressed in camera i). Each
edge keeps its own closed-form t_ij(R_ij) (null vector of its Pˢ). An observation is the
pair (view, keypoint): no track building is needed, E_ik is simply the set of edges whose
matches contain that keypoint.

Optimisation (Alg. 4, ``solve``): Levenberg-Marquardt on the 3n rotation parameters with one
view fixed (the gauge), left perturbations R_i <- exp([δ_i]x) R_i. The exact Jacobian is built
per match for the three parameters of R_ij (kernels.trrm_chunk_terms, including dt/dδ and
dω/dδ) and chained to the two cameras with δR_ij = δ_j - R_ij δ_i; ``problem.GRRMSystem``
accumulates the normal equations block by block, dense up to 200 views and sparse (SuperLU)
above.
"""

from rotonly_cli.geometry.grrm.problem import GRRMSystem, chain_matrix
from rotonly_cli.geometry.grrm.solve import (
                                            GRRMResult,
                                            epipolar_phase,
                                            grrm_residuals,
                                            optimize_global_rotations,
                                            validate_inputs,
)
from rotonly_cli.options import GRRMOptions, ResidualForm, RobustLoss

__all__ = ["GRRMOptions", "GRRMResult", "GRRMSystem", "ResidualForm", "RobustLoss", "chain_matrix", "epipolar_phase",
           "grrm_residuals", "optimize_global_rotations", "validate_inputs"]
