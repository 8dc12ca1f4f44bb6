"""The lumen's state: residual fluid and segments not fully distended (`colon.lumen`).

Sources (docs/sources.md section 3.3):
- Residual fluid after a bowel preparation, automated volumetry of 500 CT colonographies
  (250 adults, each prepared once with magnesium citrate and once with sodium phosphate):
  155 +- 114 ml and 143 +- 100 ml, under 200 ml in 77 % and 82 % (Pickhardt et al.,
  V, abstract). Drawn here from the log-normal with the two arms' pooled mean and SD,
  149 +- 107 ml (the log-normal: an assumption, U; it keeps the volume positive and skewed
  as the share under 200 ml implies: 79 % drawn).
- Distension graded per segment in 146 supine CT colonographies: 10.4 % of segments
  inadequate or collapsed, the sigmoid worst (mean score 2.68 of 4, every other segment's
  mean above 3; V, abstract); 35 % of 108 patients had at least one collapsed segment
  (McLaughlin et al. 2013, V, abstract). Drawn here: the sigmoid 35 % of the time, each
  other segment 6 %, which averages 10.8 % of segments (the split between the sigmoid and
  the rest: U) and gives 54 % of patients at least one (above the 35 % with a collapsed
  one: inadequate segments are counted too).
- A segment not fully distended is drawn round, `collapsed_fraction` of its diameter (U):
  a real one is flattened and pushed open by the capsule, which a rigid wall cannot do.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .lesions import drawn_lesions
from .params import SEGMENT_NAMES, ColonParams, Lesions, LumenState, PlacedLesion

FLUID_ML = (149.0, 107.0)
"""Residual fluid (ml), mean and SD pooled over Pickhardt et al.'s two preparations."""
COLLAPSED_CHANCE = {"sigmoid": 0.35, "rectum": 0.06, "descending": 0.06, "transverse": 0.06,
                    "ascending": 0.06, "cecum": 0.06}
"""Chance that a segment is not fully distended (10.4 % of segments overall, the sigmoid
the worst; the split: U)."""
CAPSULE_PASSAGE = 0.0068
"""Smallest lumen radius less the highest fold that the lumen keeps when a segment is
narrowed (m): the capsule's 5.8 mm radius and 1 mm to spare."""
FLUID_RGBA = (0.78, 0.66, 0.38, 0.8)
"""Colour of the liquid's surface: the yellow-brown of residual lavage fluid (U)."""
BUBBLE_RGBA = (0.95, 0.93, 0.85, 0.6)
"""Colour of the bubbles: a pale film (U)."""
BUBBLES_DRAWN = 40
"""Most bubbles drawn for a patient (uniform from 0; U)."""
BUBBLE_RADIUS = (0.0005, 0.003)
"""Smallest and largest bubble radius (m), drawn log-uniform (U)."""


@dataclasses.dataclass(frozen=True)
class DrawnLumen:
    """The lumen state of one patient, every field resolved."""

    fluid_ml: float
    collapsed: tuple[str, ...]
    collapsed_fraction: float
    bubbles: int


def drawn_lumen(params: ColonParams) -> DrawnLumen | None:
    """The lumen state of `params` with the fields left null drawn for `params.seed` (its
    own random stream, [seed, 11]); None when `params.lumen` is null."""
    lumen = params.lumen
    if lumen is None:
        return None
    rng = np.random.default_rng([params.seed, 11])
    mean, sd = FLUID_ML
    sigma = np.sqrt(np.log(1.0 + (sd / mean) ** 2))
    drawn_ml = float(np.exp(np.log(mean) - 0.5 * sigma ** 2 + sigma * rng.normal()))
    drawn_collapsed = tuple(name for name in SEGMENT_NAMES
                            if rng.uniform() < COLLAPSED_CHANCE[name])
    drawn_bubbles = int(rng.integers(0, BUBBLES_DRAWN + 1))
    fluid = lumen.fluid_ml if lumen.fluid_ml is not None else drawn_ml
    collapsed = tuple(lumen.collapsed) if lumen.collapsed is not None else (
        drawn_collapsed if params.procedural else ())
    bubbles = lumen.bubbles if lumen.bubbles is not None else drawn_bubbles
    return DrawnLumen(fluid, collapsed, lumen.collapsed_fraction, bubbles)


def geometry_params(params: ColonParams) -> ColonParams:
    """`params` as far as the colon's wall goes: the lumen's state only through the
    segments it narrows (resolved for the seed), its fluid and bubbles aside, and of the
    lesions only the diverticula (pouches cut into the wall, resolved for the seed into
    placements; polyps are geometry of their own), so that patients who differ only in
    those share one built colon and its cached files."""
    if params.lesions is not None:
        pouches = ([lesion for lesion in drawn_lesions(params) if not lesion.polyp]
                   if params.procedural else [])
        params = dataclasses.replace(params, lesions=Lesions(
            drawn=False, polyps=False, diverticula=False,
            placed=[PlacedLesion(p.kind, p.size_mm, p.segment, p.along, p.around_deg)
                    for p in pouches]) if pouches else None)
    state = drawn_lumen(params)
    if state is None:
        return params
    lumen = (LumenState(fluid_ml=0.0, collapsed=list(state.collapsed),
                        collapsed_fraction=state.collapsed_fraction, bubbles=0)
             if state.collapsed else None)
    return dataclasses.replace(params, lumen=lumen)


def narrowed(params: ColonParams) -> ColonParams:
    """`params` with the diameters of the segments that are not fully distended narrowed
    (never below what leaves the capsule CAPSULE_PASSAGE past the highest fold); `params`
    itself when none is."""
    state = drawn_lumen(params)
    if state is None or not state.collapsed:
        return params
    out = dataclasses.replace(params)
    for name in state.collapsed:
        seg = params.segment(name)
        fold = seg.fold_height * params.fold_height_scale * (1.0 + params.fold_height_jitter)
        floor = 2.0 * (CAPSULE_PASSAGE + fold)
        diameter = max(seg.diameter * state.collapsed_fraction, min(floor, seg.diameter))
        setattr(out, name, dataclasses.replace(seg, diameter=diameter))
    return out
