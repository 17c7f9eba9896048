"""Write rxj1131_quasars.reg: DS9 circles over the four quasar images of RXJ1131-1231 (F814W).

    python benchmarks/real/make_rxj1131_mask.py [--radius-pix 8] [--min-peak 10]

The quasar images are the compact peaks above `min_peak` (e-/s; the lens galaxy's peak is
~6, the quasars' 28-200) of the SCI image, found with photutils.find_peaks. They are
masked rather than modelled: clumpylen has no point-source component, and a clump at the
smallest R_e would have to fit a 200 e-/s PSF core to the PSF model's accuracy (a few %,
i.e. tens of σ). The radius (8 px = 0.4") leaves out the core and first Airy ring, where
the empirical PSF's errors (its PSF_ERR extension) exceed the noise; the fainter wings
beyond are left in the fit and show in its residuals.
"""

from __future__ import annotations

import argparse
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[1].parent / "shared" / "data" / "real" / "rxj1131" / "rxj1131_f814w.fits"


def quasar_regions(sci, min_peak: float, radius_pix: float):
    import numpy as np
    from photutils.detection import find_peaks
    from regions import CirclePixelRegion, PixCoord, Regions
    peaks = find_peaks(np.asarray(sci, float), threshold=min_peak, box_size=9)
    peaks.sort("peak_value", reverse=True)
    return Regions([CirclePixelRegion(PixCoord(float(p["x_peak"]), float(p["y_peak"])), radius_pix,
                                      meta={"text": f"QSO {i}"}) for i, p in enumerate(peaks)])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radius-pix", type=float, default=8.0)
    ap.add_argument("--min-peak", type=float, default=10.0)
    ap.add_argument("--out", default=str(HERE / "rxj1131_quasars.reg"))
    args = ap.parse_args()
    from astropy.io import fits
    regs = quasar_regions(fits.getdata(DATA, "SCI"), args.min_peak, args.radius_pix)
    regs.write(args.out, format="ds9", overwrite=True)
    print(f"wrote {args.out}: {len(regs)} circles")


if __name__ == "__main__":
    main()
