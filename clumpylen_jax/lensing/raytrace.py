"""The lens equation β = θ − α(θ)."""


def trace(lens, theta1, theta2):
    """Source-plane positions β (arcsec) of rays at lens-plane θ (arcsec)."""
    a1, a2 = lens.deflection(theta1, theta2)
    return theta1 - a1, theta2 - a2
