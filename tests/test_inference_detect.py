"""Fisher-forecast detectability and a tiny injection–recovery completeness grid."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clumpylen_jax.inference.completeness import completeness_grid, completeness_grids
from clumpylen_jax.inference.detect import clump_detectability
from clumpylen_jax.inference.mock import TOY_ACCURACY, toy_bands, toy_model
from clumpylen_jax.source import Clumps, Source


def test_detectability_orders_and_flags_blending():
    src = Source(clumps=Clumps(jnp.array([[-0.3, 0.1], [0.0, 0.0], [0.04, 0.01], [0.3, -0.3]]),
                               jnp.array([[5.0], [2.0], [2.0], [0.05]]), jnp.full(4, 0.06),
                               jnp.full(4, 0.5), jnp.ones(4), jnp.zeros(4)))
    t = clump_detectability(toy_model(src, toy_bands(1)), src)
    snr, iso = np.asarray(t["snr_flux_B0"]), np.asarray(t["snr_flux_B0_isolated"])
    assert np.all(np.isfinite(snr)) and np.all(snr <= iso * (1 + 1e-9))
    assert snr[0] > 20 and snr[3] < 1.5
    assert snr[1] / iso[1] < 0.5 < snr[0] / iso[0]  # the blended pair loses most of its S/N
    assert np.all(np.isfinite(t["snr_re"]))


@pytest.mark.slow
def test_completeness_grid_bright_found_faint_missed():
    # slow: ~22 s on 2 cores (make test took 10 min 9 s with it); the completeness grid
    # itself still runs in the study-completeness notebook test
    base = Source(clumps=Clumps(jnp.array([[0.2, 0.2]]), jnp.array([[3.0]]), jnp.array([0.06]),
                                jnp.array([0.5]), jnp.array([1.0]), jnp.array([0.0])))
    pos = np.array([[-0.2, -0.1], [0.0, -0.25], [-0.25, 0.15], [0.22, 0.12]])  # last: blended
    res = completeness_grid(base, toy_bands(1), [0.02, 3.0], [0.06], jax.random.key(0),
                            field_arcsec=((-0.45, 0.45), (-0.45, 0.45)), positions_arcsec=pos,
                            accuracy=TOY_ACCURACY)
    assert res.completeness.shape == (2, 1)
    assert res.completeness[0, 0] == 0.0
    assert res.completeness[1, 0] >= 0.75 and res.detected_fraction[1, 0] == 1.0
    assert res.blended_fraction[1, 0] >= 0.25  # the injection on top of the base clump
    assert res.fisher_snr_flux[1, 0] > 10 * res.fisher_snr_flux[0, 0]
    assert res.segment_multiplicity[2] >= 1
    assert len(res.to_table()) == 2
    # `completeness_grids`: the same injections scored plain and deblended; the plain result
    # is `completeness_grid`'s, field for field
    plain, deblended = completeness_grids(
        base, toy_bands(1), [0.02, 3.0], [0.06], jax.random.key(0),
        field_arcsec=((-0.45, 0.45), (-0.45, 0.45)), positions_arcsec=pos,
        accuracy=TOY_ACCURACY, fisher=False)
    for name in ("completeness", "detected_fraction", "blended_fraction",
                 "segment_multiplicity"):
        assert np.array_equal(getattr(plain, name), getattr(res, name)), name
    assert deblended.completeness[1, 0] >= plain.completeness[1, 0]
    assert deblended.blended_fraction[1, 0] <= plain.blended_fraction[1, 0]


def test_deblending_gives_a_clump_on_a_host_a_segment_of_its_own():
    """`completeness.detect`: a compact clump 6 pixels from the centre of a broad host lies in
    the host's segment (one segment, its centroid near the host's), and deblended it is a
    segment of its own, whose centroid lies nearer the clump than the host's centre (not on
    it: the watershed gives the clump's segment the host's light on its side, 3 pixels of
    pull here); pure numpy images."""
    from clumpylen_jax.inference.completeness import _centroids, detect
    yy, xx = np.mgrid[:61, :61] - 30.0
    host = 50.0 * np.exp(-np.hypot(xx, yy) / 6.0)
    clump = 40.0 * np.exp(-0.5 * ((xx - 6.0) ** 2 + (yy - 2.0) ** 2) / 1.2**2)
    img = host + clump + np.random.default_rng(0).normal(0.0, 0.5, host.shape)
    plain = detect(img, 0.5, nsigma=3.0, npixels=5)
    deblended = detect(img, 0.5, nsigma=3.0, npixels=5, deblend=True)
    r, c = 32, 36           # the clump's peak pixel (row = y, col = x)
    assert plain[r, c] > 0 and plain[r, c] == plain[30, 30]
    assert deblended[r, c] > 0 and deblended[r, c] != deblended[30, 30]
    cy, cx = _centroids(img, deblended)[int(deblended[r, c])]
    assert np.hypot(cy - r, cx - c) < np.hypot(cy - 30, cx - 30), (cy, cx)
