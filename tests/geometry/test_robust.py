"""Robust losses: ρ' and the curvature terms against finite differences of ρ."""

import numpy as np
import pytest

from rotonly_cli.geometry import robust

LOSSES = ["none", "huber", "cauchy", "geman_mcclure"]


@pytest.mark.parametrize("loss", LOSSES)
def test_first_and_second_derivatives_match_finite_differences(loss):
    scale = 0.7
    s = np.geomspace(1e-3, 30.0, 200)
    s = s[np.abs(s - scale**2) > 1e-2]  # Huber's kink
    h = 1e-6 * s
    rho, drho = robust.robust_rho(s, loss, scale)
    rho_p, drho_p = robust.robust_rho(s + h, loss, scale)
    rho_m, drho_m = robust.robust_rho(s - h, loss, scale)
    np.testing.assert_allclose(drho, (rho_p - rho_m) / (2 * h), rtol=1e-6, atol=1e-12)
    # β = -2 s ρ'' / ρ' unclamped = clamped part + radial excess
    d2rho = (drho_p - drho_m) / (2 * h)
    beta = -2 * s * d2rho / drho
    clamped = robust.robust_curvature(s, loss, scale)
    excess = robust.radial_excess(s, loss, scale)
    if loss == "huber":  # β = 1 beyond the scale (ρ'' = -ρ'/(2s)); curvature clamps it to 1 there
        np.testing.assert_allclose(clamped, (s > scale**2).astype(float))
        return
    np.testing.assert_allclose(np.minimum(np.maximum(beta, 0), 1), clamped, atol=1e-5)
    np.testing.assert_allclose(np.maximum(beta - 1, 0), excess, atol=1e-5)


def test_geman_mcclure_redescends():
    """The influence ψ(r) = r ρ'(r²) of Geman-McClure falls to zero far out; Cauchy's does not
    fall faster than 1/r."""
    r = np.array([1.0, 10.0, 100.0])
    _, gm = robust.robust_rho(r**2, "geman_mcclure", 1.0)
    _, cauchy = robust.robust_rho(r**2, "cauchy", 1.0)
    psi_gm, psi_c = r * gm, r * cauchy
    assert psi_gm[2] < 1e-5 and psi_gm[2] < psi_gm[1] < psi_gm[0]
    np.testing.assert_allclose(psi_c * r, r**2 / (1 + r**2), rtol=1e-12)  # ψ = r / (1 + r²)
