"""Physical and unit constants, each written once (import them; do not retype them).

ARCSEC_PER_RAD: arcseconds in one radian, 180/π × 3600 (exact to float64).
C_KMS: the speed of light in km/s (exact by the SI definition of the metre).
"""

import math

ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0
ARCSEC_PER_DEG = 3600.0
C_KMS = 299792.458
