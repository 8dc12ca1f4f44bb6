"""The patient: procedural, imported and ex vivo colons in a supine abdomen, one loader."""

from .abdomen import Abdomen
from .cache import GEOMETRY_VERSION, ColonAssets, default_cache_root, params_hash
from .centerline import Centerline
from .colon import Colon, TubeColon, build_colon
from .params import (SEGMENT_NAMES, AbdomenParams, ColonParams, MucosaParams, SegmentParams,
                     check_colon_params)
from .pieces import wall_pieces
from .source import ColonSourceError, colon_assets, colon_wall_pieces, load_colon
from .wall import HaustralWall

__all__ = [
    "Abdomen", "AbdomenParams", "Centerline", "Colon", "ColonAssets", "ColonParams",
    "ColonSourceError", "GEOMETRY_VERSION", "HaustralWall", "MucosaParams", "SEGMENT_NAMES",
    "SegmentParams", "TubeColon", "build_colon", "check_colon_params", "colon_assets",
    "colon_wall_pieces", "default_cache_root", "load_colon", "params_hash", "wall_pieces",
]
