"""The label codes of a segmentation: one vocabulary for every stage that reads label maps.

0 background (air and thorax interior), 1 breast tissue, 2 muscle / chest wall, 3 glandular
tissue (inside the breast, optional). The breast of the convention includes the gland
(:data:`BREAST_TISSUE`). Region codes of a mesh are another vocabulary
(``mechanics.mesh.REGIONS``: left and right breast apart).
"""

from __future__ import annotations

BACKGROUND, BREAST, MUSCLE, GLAND = 0, 1, 2, 3
#: Every code a label map may hold.
KNOWN_LABELS = (BACKGROUND, BREAST, MUSCLE, GLAND)
#: Codes that make up the breast (fat and gland).
BREAST_TISSUE = (BREAST, GLAND)
#: Code -> name.
LABEL_NAMES = {BACKGROUND: "background", BREAST: "breast", MUSCLE: "muscle", GLAND: "gland"}
#: Code -> name of the tissues (background left out).
TISSUES = {code: name for code, name in LABEL_NAMES.items() if code != BACKGROUND}
#: Code -> matplotlib colour of the tissues' contours.
LABEL_COLOURS = {BREAST: "tab:orange", MUSCLE: "tab:red", GLAND: "tab:green"}
#: Code -> RGB 0-255, the same colours (colour tables for Slicer and ParaView).
LABEL_RGB = {BACKGROUND: (0, 0, 0), BREAST: (255, 127, 14), MUSCLE: (214, 39, 40),
             GLAND: (44, 160, 44)}
