"""Typed survey containers and their on-disk format."""

from sss2bathy.survey.errors import SurveyFormatError
from sss2bathy.survey.grid import BathyGrid
from sss2bathy.survey.masks import (
    MASK_NO_HIT,
    MASK_OUT_OF_BEAM,
    MASK_SHADOW,
    MASK_VALID,
    MASK_WATER_COLUMN,
    mask_reason_counts,
)
from sss2bathy.survey.model import AltimeterPoints, SensorParams, SidescanLine, Survey

__all__ = [
    "AltimeterPoints",
    "BathyGrid",
    "MASK_NO_HIT",
    "MASK_OUT_OF_BEAM",
    "MASK_SHADOW",
    "MASK_VALID",
    "MASK_WATER_COLUMN",
    "SensorParams",
    "SidescanLine",
    "Survey",
    "SurveyFormatError",
    "mask_reason_counts",
]
