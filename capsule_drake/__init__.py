"""capsule_drake: magnetically actuated endoscopic capsules in the colon, as a Drake diagram."""

__version__ = "0.1.0"
