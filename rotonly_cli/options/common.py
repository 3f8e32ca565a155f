"""The choices of rotonly's options (StrEnums), their shared constants and checks."""

from __future__ import annotations

from rotonly_cli.compat import StrEnum
from rotonly_cli.errors import InputError

# ============================================================================ choices

class RobustLoss(StrEnum):
    """Robust loss ρ(s) of a squared residual norm s (geometry/robust.py)."""

    NONE = "none"  #: plain least squares (the paper's)
    HUBER = "huber"  #: ρ(s) = s inside the scale, linear in √s beyond
    CAUCHY = "cauchy"  #: ρ(s) = c² log(1 + s/c²)
    #: ρ(s) = c² s / (c² + s): redescending, a residual far beyond c has no pull at all
    GEMAN_MCCLURE = "geman_mcclure"


class ResidualForm(StrEnum):
    """Units of GRRM's residual V_ik."""

    IMAGE = "image"  #: normalized image coordinates (eq:GRRMRes1 with eq:PA2/PA3, BA's units)
    BEARING = "bearing"  #: unit-sphere differences (eq:PA3bearing, TRRM's form)


class RobustWeight(StrEnum):
    """IRLS kernel of rotation averaging (algorithms.md §2.1 step 5)."""

    GEMAN_MCCLURE = "geman_mcclure"  #: ICCV 2013; COLMAP default
    HALF_NORM = "half_norm"  #: ℓ½, TPAMI 2018 / ROBA / the seed's Chatterjee baseline
    L2 = "l2"  #: no robustness (for tests and ablations)


class Reestimate(StrEnum):
    """Which stored relative poses the load stage re-estimates with calibrated RANSAC."""

    AUTO = "auto"  #: edges without an E-based stored pose (PLANAR, UNCALIBRATED, ..., none stored)
    ALL = "all"  #: every edge
    NONE = "none"  #: none: edges without a usable stored pose are filtered


class Consensus(StrEnum):
    """How the load stage settles each edge's inlier matches from its seeded RANSAC runs."""

    #: ``FAST`` on a load of at least ``LoadOptions.agreement_min_edges`` edges (a collection),
    #: ``FULL`` on fewer (a scene, where one pair's wrong model bends the views)
    AUTO = "auto"
    #: ``LoadOptions.consensus_runs`` runs on every edge, the matches every run accepts kept
    FULL = "full"
    #: on edges of more than ``agreement_min_matches`` matches, two runs on a subset that agree
    #: are kept as they are (``LoadOptions.consensus_agreement``): cheaper, less robust
    FAST = "fast"


class Intrinsics(StrEnum):
    """What ``rotonly run`` does with the camera intrinsics it is given (calibration/)."""

    FIXED = "fixed"  #: used as given
    #: every camera calibrated: focal lengths from the view graph, then focal, principal point
    #: and radial terms estimated from the reconstruction
    REFINE = "refine"
    #: cameras the input marks as a guess (COLMAP ``prior_focal_length = 0``) calibrated as
    #: ``refine`` does, cameras whose reprojection error shows them wrong, and cameras whose
    #: principal point sits at the image centre (a default) where one adjustment moves it
    #: significantly; the others stay as given
    AUTO = "auto"


#: fewest matches an edge may have (five-point minimum + one to over-determine Pˢ)
MIN_MATCHES = 6
LOSSES = tuple(loss.value for loss in RobustLoss)
RESIDUALS = tuple(form.value for form in ResidualForm)
REESTIMATE_MODES = tuple(mode.value for mode in Reestimate)
INTRINSICS_MODES = tuple(mode.value for mode in Intrinsics)
CONSENSUS_MODES = tuple(mode.value for mode in Consensus)


def cluster_address(address: str) -> tuple[str, int | str]:
    """``--cluster``: ("local", N) for ``local:N`` (a LocalCluster of N worker processes,
    N >= 1), ("remote", address) for ``tcp://HOST:PORT`` (a running Dask scheduler);
    InputError naming --cluster otherwise (runtime/cluster.py)."""
    text = str(address).strip()
    if text.startswith("local:"):
        count = text.removeprefix("local:")
        if count.isdigit() and int(count) >= 1:
            return "local", int(count)
        raise InputError(f"{address!r}: local:N needs a number of workers N >= 1", field="--cluster")
    if text.startswith("tcp://"):
        host, _, port = text.removeprefix("tcp://").rpartition(":")
        if host and port.isdigit() and 0 < int(port) < 65536:
            return "remote", text
    raise InputError(f"{address!r}: expected tcp://HOST:PORT (a running Dask scheduler) or local:N",
                     field="--cluster")


# ============================================================================ geometry

def _require_non_negative(options, *names: str, none_allowed: bool = False) -> None:
    """ValueError naming the first of ``names`` that is negative (or NaN; or None unless
    ``none_allowed``)."""
    for name in names:
        value = getattr(options, name)
        if none_allowed and value is None:
            continue
        if not value >= 0:
            raise ValueError(f"{name}: must be >= 0 or None" if none_allowed else f"{name}: must be >= 0")
