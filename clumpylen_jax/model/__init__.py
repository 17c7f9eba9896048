"""The forward model of a scene, composed of small Modules (CONTRIBUTING.md, "Where to
change what"):

- `scene_model`: `build_model` (chooses the renderers) and `SceneModel` (adds up their
  light per band and hands it to the detectors);
- `renderer`: the `Renderer` interface and the light a renderer returns;
- `hosts`, `clumps`: the renderers (unlensed, through the lens plane, analytic, ray-traced
  on a source-plane grid, linearised);
- `lensplane`: the traced lens plane the lensed renderers share;
- `detector`: `Band` and `DetectorBand` (pixel grid, PSF, sky, exposure, noise).
"""

from ..accuracy import ACCURACY_PRESETS, SOURCE_MODES, Accuracy
from .detector import Band, DetectorBand
from .scene_model import SceneModel, build_model, require_float64_mode, source_extent

__all__ = ["ACCURACY_PRESETS", "SOURCE_MODES", "Accuracy", "Band", "DetectorBand", "SceneModel",
           "build_model", "require_float64_mode", "source_extent"]
