"""Fast per-edge kernels of TRRM, GRRM and scene identification, in structure-of-arrays form.

``soa``: vector helpers and edge groups; ``forward``: per-match TRRM / λ_min(Pˢ) terms and
their per-edge sums (GRRM, tests); ``match_table`` + ``lean``: the lean per-edge evaluator of
TRRM's LM; ``moments``: moment-based λ_min(Pˢ), medians, the pure-rotation fit.
"""

from rotonly_cli.geometry.kernels.forward import (
                                                  epipolar_normal_equations,
                                                  trrm_chunk_terms,
                                                  trrm_match_terms,
                                                  trrm_normal_equations,
)
from rotonly_cli.geometry.kernels.lean import COST, GRADIENT, NORMAL, smallest_eigenpair_lean, trrm_evaluate
from rotonly_cli.geometry.kernels.match_table import LEAN_CHUNK, TABLE_ROWS, MatchTable
from rotonly_cli.geometry.kernels.moments import (
                                                  bearing_cross_moment,
                                                  best_pure_rotation,
                                                  epipolar_from_moments,
                                                  epipolar_moments,
                                                  point_moments,
                                                  rotated_bearing_sq,
                                                  segment_median,
)
from rotonly_cli.geometry.kernels.soa import CHUNK_MATCHES, dot, edge_chunks

__all__ = [
    "CHUNK_MATCHES", "COST", "GRADIENT", "LEAN_CHUNK", "NORMAL", "TABLE_ROWS", "MatchTable", "bearing_cross_moment",
    "best_pure_rotation", "dot", "edge_chunks", "epipolar_from_moments", "epipolar_moments",
    "epipolar_normal_equations", "point_moments", "rotated_bearing_sq", "segment_median", "smallest_eigenpair_lean",
    "trrm_chunk_terms", "trrm_evaluate", "trrm_match_terms", "trrm_normal_equations",
]
