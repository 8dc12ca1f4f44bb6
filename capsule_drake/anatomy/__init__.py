"""Procedural, anatomically dimensioned colon (rectum to cecum) in a supine abdomen."""

from .abdomen import Abdomen
from .centerline import Centerline
from .colon import (GEOMETRY_VERSION, Colon, ColonAssets, build_colon, colon_assets,
                    default_cache_root, params_hash)
from .params import (SEGMENT_NAMES, AbdomenParams, ColonParams, MucosaParams, SegmentParams,
                     check_colon_params)
from .pieces import wall_pieces
from .wall import HaustralWall

__all__ = [
    "Abdomen", "AbdomenParams", "Centerline", "Colon", "ColonAssets", "ColonParams",
    "GEOMETRY_VERSION", "HaustralWall", "MucosaParams", "SEGMENT_NAMES", "SegmentParams", "build_colon",
    "check_colon_params", "colon_assets", "default_cache_root", "params_hash", "wall_pieces",
]
