"""Polyps and diverticula drawn for a patient (`colon.lesions`).

Each figure below is cited with its status in docs/sources.md section 3.4; in short:
- Polyps: at least one in 45 % of screening colonoscopies (Lieberman et al. 2008, 13,992
  patients). How many, given at least one: 1 + Poisson(1.3), a mean of 2.3 (U: the ratio of
  adenomas per colonoscopy to the adenoma detection rate in a trial's control arm, Repici et
  al. 2022, 1.04 / 0.445; the shape of the count is an assumption).
- Size class of a polyp: <= 5 mm 73.6 %, 6-9 mm 22.7 %, >= 10 mm 3.7 % (the routine arm of
  a randomised trial, 269 polyps); within a class, the size uniform over the sizes that
  round to 2-5 mm or to 6-9 mm, or log-uniform over 10-30 mm (U).
- Segment of a polyp: rectum 25.7, sigmoid 29.4, descending 9.7, transverse 16.7,
  ascending 17.5, cecum 1.1 % (the same 269 polyps).
- Shape (Paris classification) by size class, from the SUN database's 100 polyps (counted
  here from its published per-polyp table): <= 5 mm: 0-Ip 2 of 60 (0-Isp counted as 0-Ip),
  0-Is 34, 0-IIa 24; 6-9 mm: 3, 11, 6 of 20; >= 10 mm: 12, 4, 4 of 20.
- Diverticula: at least one in 42 % of screening colonoscopies (Peery et al. 2016, 624
  patients, mean age 54), 14 per affected patient on average (range 1-158): drawn
  1 + a negative binomial with that mean and a spread that reaches the range (U); by
  segment sigmoid 75 %, descending 11 %, transverse 6 %, ascending 8 % (white patients;
  none in the rectum); neck 5-10 mm (S: a guideline's "typically 5-10 mm"; uniform, U).
- Where along its segment and around the lumen: uniform (U).

A patient keeps their lesions: they are drawn from their own stream ([seed, 23]), so
another option of the colon does not move them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .params import PARIS_TYPES, SEGMENT_NAMES, ColonParams

POLYP_PREVALENCE = 0.45
"""Share of screening patients with at least one polyp (Lieberman et al. 2008)."""
EXTRA_POLYPS_MEAN = 1.3
"""Mean of the Poisson count of polyps beyond the first in a patient who has one (U)."""
SIZE_CLASSES = ("diminutive", "small", "large")
"""<= 5 mm, 6-9 mm, >= 10 mm."""
SIZE_CLASS_SHARE = (0.736, 0.227, 0.037)
SIZE_RANGE_MM = ((2.0, 5.0), (6.0, 9.0), (10.0, 30.0))
POLYP_SEGMENT_SHARE = {"rectum": 0.257, "sigmoid": 0.294, "descending": 0.097,
                       "transverse": 0.167, "ascending": 0.175, "cecum": 0.011}
"""Share of polyps per segment (the same trial arm; sums to 1.001 as published)."""
PARIS_COUNTS = {"diminutive": (2, 34, 24), "small": (3, 11, 6), "large": (12, 4, 4)}
"""SUN database polyps per size class as (0-Ip, 0-Is, 0-IIa) (0-Isp counted with 0-Ip)."""
DIVERTICULOSIS_PREVALENCE = 0.42
DIVERTICULA_MEAN = 14.0
DIVERTICULA_DISPERSION = 1.0
"""Shape of the negative binomial of the count beyond the first (U: 1 is a geometric
count, whose tail reaches Peery's 158 in about 1 of 10,000 affected patients)."""
DIVERTICULA_MAX = 160
DIVERTICULUM_SEGMENT_SHARE = {"rectum": 0.0, "sigmoid": 0.75, "descending": 0.11,
                              "transverse": 0.06, "ascending": 0.08, "cecum": 0.0}
DIVERTICULUM_NECK_MM = (5.0, 10.0)


@dataclasses.dataclass(frozen=True)
class DrawnLesion:
    """One lesion of a patient, before it is placed on the built wall."""

    kind: str            # a Paris type (PARIS_TYPES) or "diverticulum"
    size_mm: float       # largest diameter (a diverticulum's neck)
    segment: str
    along: float         # 0 at the segment's anal end, 1 at its other end
    around_deg: float    # 0 on the floor, 180 on the roof

    @property
    def polyp(self) -> bool:
        return self.kind != "diverticulum"

    @property
    def size_class(self) -> str:
        """A polyp's: diminutive (<= 5 mm), small (6-9 mm) or large (>= 10 mm), read with
        the sizes rounded to the millimetre, as endoscopists report them; "diverticulum"
        for a diverticulum."""
        if not self.polyp:
            return "diverticulum"
        size = round(self.size_mm)
        return "diminutive" if size <= 5 else "small" if size <= 9 else "large"


def _shares(table: dict) -> np.ndarray:
    values = np.array([table[name] for name in SEGMENT_NAMES], float)
    return values / values.sum()


def draw_polyps(rng) -> list[DrawnLesion]:
    """The polyps of one patient drawn from `rng` (module docstring)."""
    if rng.uniform() >= POLYP_PREVALENCE:
        return []
    count = 1 + int(rng.poisson(EXTRA_POLYPS_MEAN))
    segment_shares = _shares(POLYP_SEGMENT_SHARE)
    polyps = []
    for _ in range(count):
        k = int(rng.choice(3, p=SIZE_CLASS_SHARE))
        low, high = SIZE_RANGE_MM[k]
        size = (float(np.exp(rng.uniform(np.log(low), np.log(high)))) if k == 2
                else float(rng.uniform(low - 0.49, high + 0.49)))
        counts = np.array(PARIS_COUNTS[SIZE_CLASSES[k]], float)
        kind = PARIS_TYPES[int(rng.choice(3, p=counts / counts.sum()))]
        segment = SEGMENT_NAMES[int(rng.choice(len(SEGMENT_NAMES), p=segment_shares))]
        polyps.append(DrawnLesion(kind, size, segment, float(rng.uniform()),
                                  float(rng.uniform(0.0, 360.0))))
    return polyps


def draw_diverticula(rng) -> list[DrawnLesion]:
    """The diverticula of one patient drawn from `rng` (module docstring)."""
    if rng.uniform() >= DIVERTICULOSIS_PREVALENCE:
        return []
    extra_mean = DIVERTICULA_MEAN - 1.0
    r = DIVERTICULA_DISPERSION
    count = min(1 + int(rng.negative_binomial(r, r / (r + extra_mean))), DIVERTICULA_MAX)
    shares = _shares(DIVERTICULUM_SEGMENT_SHARE)
    low, high = DIVERTICULUM_NECK_MM
    return [DrawnLesion("diverticulum", float(rng.uniform(low, high)),
                        SEGMENT_NAMES[int(rng.choice(len(SEGMENT_NAMES), p=shares))],
                        float(rng.uniform()), float(rng.uniform(0.0, 360.0)))
            for _ in range(count)]


def drawn_lesions(params: ColonParams) -> list[DrawnLesion]:
    """The lesions of the patient `params` describes: the drawn ones (for `lesions.seed`, or
    `colon.seed`), then the placed ones; [] when `params.lesions` is null."""
    config = params.lesions
    if config is None:
        return []
    lesions = []
    if config.drawn:
        seed = params.seed if config.seed is None else config.seed
        polyps_rng = np.random.default_rng([seed, 23, 0])
        diverticula_rng = np.random.default_rng([seed, 23, 1])
        if config.polyps:
            lesions += draw_polyps(polyps_rng)
        if config.diverticula:
            lesions += draw_diverticula(diverticula_rng)
    lesions += [DrawnLesion(p.kind, float(p.size_mm), p.segment, float(p.along),
                            float(p.around_deg)) for p in config.placed]
    return lesions
