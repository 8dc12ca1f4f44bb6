"""Camera optics of the capsule: lens models (pixels <-> rays), independent of Drake."""

from .lens import FISHEYE_MODELS, MODELS, Lens, LensConfig

__all__ = ["FISHEYE_MODELS", "Lens", "LensConfig", "MODELS"]
