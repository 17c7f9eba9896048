"""Built-in look-alike clusters, lens components from tables, and the diagnostic plot."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clumpylen_jax.errors import ConfigError
from clumpylen_jax.lensing import find_images, lens_plane_region
from clumpylen_jax.lensing.clusters import builtin_lens, builtin_lens_info, lens_from_components, load_builtin_spec
from clumpylen_jax.lensing.plots import plot_lens

MACS_BETA = (-13.716581, 3.6176634)
MACS_IMAGES = np.array([(-35.57, 18.85), (-42.66, 8.46), (-20.16, 31.53)])
A2744_BETA = (28.395195, 40.2729467)


def _valid(im):
    v = np.asarray(im.valid)
    return np.stack([np.asarray(im.theta1)[v], np.asarray(im.theta2)[v]], 1), np.asarray(im.magnification)[v]


def test_macs0416_like_reproduces_the_paper_configuration():
    lens = builtin_lens("macs0416-like", 6.145)
    assert builtin_lens_info("macs0416-like")["z_lens"] == pytest.approx(0.396)
    im = find_images(lens, *MACS_BETA, field=((-48.0, -15.0), (0.0, 35.0)), pixel_arcsec=0.3, max_images=6)
    th, mu = _valid(im)
    # the paper's three images, plus the merging partners of the arc (β sits inside the cusp)
    assert 3 <= len(th) <= 5
    for p in MACS_IMAGES:
        assert np.min(np.hypot(*(th - p).T)) < 1.0
    arc = np.argmin(np.hypot(*(th - MACS_IMAGES[0]).T))
    assert 10 <= abs(mu[arc]) <= 30


def test_a2744_like_gives_a_highly_magnified_double_arc():
    lens = builtin_lens("a2744-like", 3.98)
    spec = load_builtin_spec("a2744-like")
    assert "look-alike" in spec["description"].lower() or "look-alike" in spec["provenance"]["constraints"]
    im = find_images(lens, *A2744_BETA, field=((40.0, 65.0), (50.0, 75.0)), pixel_arcsec=0.25, max_images=6)
    th, mu = _valid(im)
    big = np.abs(mu) >= 20
    assert big.sum() >= 2  # a fold pair
    assert np.all(np.abs(mu[big]) <= 200)


def test_components_from_tables():
    lens = lens_from_components([{"kind": "sis", "theta_e_arcsec": 1.0, "center_arcsec": [0.0, 0.0]},
                                 {"kind": "shear", "gamma1": 0.1, "gamma2": 0.0}], scale=0.5)
    a1, a2 = lens.deflection(jnp.array(2.0), jnp.array(0.0))
    assert float(a1) == pytest.approx(0.5 * (1.0 + 0.2))
    with pytest.raises(ConfigError, match="kind"):
        lens_from_components([{"kind": "blob"}])
    with pytest.raises(ConfigError, match="theta_e"):
        lens_from_components([{"kind": "sis", "center_arcsec": [0, 0]}])
    with pytest.raises(ConfigError):
        lens_from_components([{"kind": "sis", "theta_e_arcsec": 1.0, "center_arcsec": [0, 0], "qq": 1}])
    with pytest.raises(ConfigError):
        builtin_lens("macs1149-like", 2.0)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_builtin_lens_is_finite_at_halo_centres(dtype):
    lens = builtin_lens("macs0416-like", 6.145)
    centres = [c["center_arcsec"] for c in load_builtin_spec("macs0416-like")["components"] if "b0_arcsec" in c]
    for c in centres:
        th = jnp.asarray(c, dtype)
        v, g = jax.value_and_grad(lambda t: jnp.sum(jnp.stack(lens.deflection(t[0], t[1]))))(th)
        assert np.isfinite(v) and np.all(np.isfinite(g))


def test_region_and_plot(tmp_path):
    lens = builtin_lens("macs0416-like", 6.145)
    box = lens_plane_region(lens, MACS_BETA, 0.3, search_field=((-48.0, -15.0), (0.0, 35.0)), pixel_arcsec=0.5,
                            margin_arcsec=0.5, component=tuple(MACS_IMAGES[0]))
    (x0, x1), (y0, y1) = box
    assert x0 < MACS_IMAGES[0][0] < x1 and y0 < MACS_IMAGES[0][1] < y1
    assert x1 - x0 < 25 and y1 - y0 < 25  # only the main arc
    out = plot_lens(lens, MACS_BETA, tmp_path / "macs.png", field=((-48.0, -15.0), (0.0, 35.0)),
                    pixel_arcsec=0.3, source_radius_arcsec=0.3)
    assert out.is_file() and out.stat().st_size > 10_000
    assert not list(tmp_path.glob("*.tmp"))
