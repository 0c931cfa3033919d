"""Figures a person would rather look at than read.

- `ssm`: SSM compactness and quality curves, shape-mode variation (renders).
- `cohort`: histograms of the virtual cohort's spinopelvic parameters with the patients and the inclusion
  thresholds, and the mesh-quality summary.
- `models`: the hex mean model by part and the gallery of personalized models (renders).
- `rom`: range-of-motion validation, ROM per shape mode, material sensitivity.
- `render`: the off-screen render of a hex model coloured by tissue (pyvista; VTK falls back to EGL/OSMesa
  software rendering without a display), its colours (shared with the platform), its cameras.
- `canvas`: the pixel-exact matplotlib canvas every figure is drawn on.

Every figure is written at exactly the pixel size it is given (no tight bounding box); 3-D renders are
placed onto the canvas pixel for pixel.  Views: lateral = from the patient's right (+x in the RAS frame of
``landmarks``), anterior to the right; frontal = from anterior (+y), z up; parallel projection.
"""

import matplotlib

# before any submodule imports pyplot: figures are written to files, never shown
matplotlib.use("Agg")
