"""Sidescan draping: georeference every bin on an MBES grid or mesh (paper section II-A).

``drape_line`` ray-traces one line; ``drape_survey`` drapes a survey with a file cache;
``DrapedLine`` is the per-bin result (points, head-plane normal n_lat, grazing angle, mask).
"""

from sss2bathy.draping.cache import drape_key, drape_survey
from sss2bathy.draping.config import DrapeConfig
from sss2bathy.draping.drape import as_surface, drape_line
from sss2bathy.draping.draped import DrapedLine
from sss2bathy.draping.surface import DrapeSurface

__all__ = [
    "DrapeConfig",
    "DrapeSurface",
    "DrapedLine",
    "as_surface",
    "drape_key",
    "drape_line",
    "drape_survey",
]
