"""The patient's colon wall: its thickness, circumferential modulus, support and friction drawn
for each patient of the population (`colon.source: !Population {...}`), from the published
spreads, or set at a named corner or a percentile of them.

`patient_wall(config, colon_params)` is the compliant wall's config with the patient's
figures in place of the nominal ones; the nominal config unchanged for a colon that is not
drawn from the population, for `tissue: nominal`, and for a contact model without the
wall's tissue figures (the rigid stand-in: its wall does not yield, so there is nothing of
the tissue's to draw). Sources and status of every figure: docs/sources.md section 3.6.

The distributions (`SPREADS`), each of the value across patients, independent of one another
(U: no source read gives their correlations), each truncated to [low, high] and drawn by its
quantile (`Spread.quantile`), so that a percentile is the same number whether drawn or asked:

- thickness: log-normal with the published mean and SD, 2.61 +- 1.29 mm (healthy controls,
  20 MHz endoscopic mini-probe ultrasound in vivo, V). Not a normal: the SD is half the mean,
  and a normal puts 2 % of walls at or below zero thickness. Truncated to [1, 6] mm: thinner
  than 1 mm is thinner than the rectum's mucosa alone (0.66-1.13 mm, EUS), and 6 mm is past
  the mean wall of sigmoid diverticular disease (5.69 mm, the same study): a healthy
  patient's wall is not that (the truncation's bounds: U). The truncation removes 3.5 % and
  2.2 % of the parent: the drawn walls are 2.57 +- 1.05 mm, median 2.36.
- circumferential modulus: log-normal with the published mean and SD at 1 cm/s, 0.63 +-
  1.25 MPa (human cadaver colon, 336 specimens of 28 colons, uniaxial tension; Massalou
  2019, V). The SD is twice the mean: a normal would draw 31 % of walls with a negative
  modulus. The specimens' spread is taken as the patients' (U: it includes the spread
  between sites of one colon and between specimens, so it overstates the patients').
  Truncated to the parent's 1st and 99th percentiles, 15 kPa and 5.4 MPa (the top at the
  stiffest human colon figure read, Christensen 2015's 5.18 MPa for rectum and sigmoid): the
  drawn walls are 0.55 +- 0.73 MPa, median 0.28 MPa; the nominal 0.63 MPa is the 74th
  percentile. The published SD is carried by its top 1 %.
- support: log-uniform over [1e5, 1e7] Pa/m, the non-zero part of the range the support is
  swept over (benchmarks/bench_tissue.py). No source gives it (U): every factor of ten in
  the range equally likely; the nominal 3e5 Pa/m is the 24th percentile, and 1e7 is what
  Johnson et al.'s porcine indentation stiffness under a colonoscope's head would need.
- friction: log-normal with median the colon's one figure, 0.09 (a colonoscope shaft on
  human colonic mucosa at the best lubricant, Watanabe 2024, S), so that the median patient
  has the nominal friction. No source gives its spread between patients (U): it is that of
  one edgeless sled on pig small-bowel mucosa across speeds, in situ and in vitro, 0.007 to
  0.054 (Lyle 2013, a factor of 7.7), taken as the span from the 5th to the 95th percentile
  (log-SD 0.62). Truncated to the parent's 1st and 99th percentiles, 0.021 and 0.38.
  Watanabe's 0.09 was the lowest coefficient reached over the lubricants tried: a reading of
  it as a lower bound would put the spread above it.

The thickness, the circumferential modulus and the support make the wall stiff or soft
together (the foundation modulus grows with each: physics/contact/compliant.py); friction
makes it sticky or slippery. A named corner (`CORNERS`) puts the first three at one
percentile and friction at another; `tissue_percentile` puts all four at the same one (low:
a thin, soft, loosely held, slippery wall). The through-thickness modulus and the
dissipation stay the scenario's (neither has a published spread; the first barely counts).

Draws are the patient's: the stream [colon.seed, TISSUE_STREAM], of its own, so that no
other stream the patient is drawn from (its length and course, lumen, lesions) changes,
and the same seed has the same wall whatever else the scenario asks for.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.special import ndtr, ndtri

from capsule_drake.schema import need_range

TISSUE_STREAM = 31
"""The patient's tissue stream: numpy's default_rng([colon.seed, TISSUE_STREAM]) (the
population's other streams: [seed, 1], [seed, 7, ...], [seed, 11], [seed, 12, ...],
[seed, 23, ...])."""


@dataclasses.dataclass(frozen=True)
class Spread:
    """One quantity's distribution across patients, as the distribution of its logarithm:
    "lognormal" (normal in the log, `mu` and `sigma` its mean and SD) or "loguniform"
    (uniform in the log), truncated to [low, high] (in the quantity's units)."""

    family: str
    mu: float
    sigma: float
    low: float
    high: float
    unit: str
    source: str

    def _cdf_parent(self, value: float) -> float:
        if self.family == "loguniform":
            return float(np.clip(math.log(value / self.low) / math.log(self.high / self.low),
                                 0.0, 1.0))
        return float(ndtr((math.log(value) - self.mu) / self.sigma))

    def quantile(self, q: float) -> float:
        """The value at probability q (0-1) of the truncated distribution."""
        if self.family == "loguniform":
            return float(self.low * (self.high / self.low) ** q)
        a, b = self._cdf_parent(self.low), self._cdf_parent(self.high)
        value = math.exp(self.mu + self.sigma * float(ndtri(a + q * (b - a))))
        return float(min(max(value, self.low), self.high))   # rounding at q = 0 or 1

    def cdf(self, value: float) -> float:
        """The probability (0-1) of a drawn value at most `value`."""
        if value <= self.low:
            return 0.0
        if value >= self.high:
            return 1.0
        a, b = self._cdf_parent(self.low), self._cdf_parent(self.high)
        return (self._cdf_parent(value) - a) / (b - a)


def lognormal(mean: float, sd: float, low: float | None = None, high: float | None = None,
              *, unit: str, source: str, tail: float = 0.01) -> Spread:
    """The log-normal of this mean and SD (log-SD sqrt(ln(1 + (sd / mean)^2))), truncated
    to [low, high], by default its `tail` and 1 - `tail` quantiles."""
    sigma = math.sqrt(math.log(1.0 + (sd / mean) ** 2))
    return lognormal_median(mean * math.exp(-0.5 * sigma**2), sigma, low, high, unit=unit,
                            source=source, tail=tail)


def lognormal_median(median: float, sigma: float, low: float | None = None,
                     high: float | None = None, *, unit: str, source: str,
                     tail: float = 0.01) -> Spread:
    """The log-normal of this median and log-SD, truncated as `lognormal`."""
    mu = math.log(median)
    low = math.exp(mu + sigma * float(ndtri(tail))) if low is None else low
    high = math.exp(mu + sigma * float(ndtri(1.0 - tail))) if high is None else high
    return Spread("lognormal", mu, sigma, float(low), float(high), unit, source)


FRICTION_SPAN = (0.007, 0.054)
"""Lyle et al. 2013 (Tribol Lett 51:377): the COF of one edgeless steel sled on pig small
bowel, across speeds, in situ and in vitro (V, abstract): its ratio is the friction's spread
from the 5th to the 95th percentile (U)."""

SPREADS = {
    "thickness": lognormal(
        2.61e-3, 1.29e-3, 1.0e-3, 6.0e-3, unit="m",
        source="2.61 +- 1.29 mm, EUS in vivo (Surg Laparosc Endosc Percutan Tech 25:205, "
               "2015); truncated to [1, 6] mm"),
    "circumferential_modulus": lognormal(
        0.63e6, 1.25e6, unit="Pa",
        source="0.63 +- 1.25 MPa at 1 cm/s, human colon, circumferential (Massalou et al., "
               "J Biomech 91:102, 2019); truncated to its 1st-99th percentiles"),
    "support_stiffness": Spread(
        "loguniform", 0.0, 0.0, 1.0e5, 1.0e7, "Pa/m",
        "no source (U): log-uniform over the swept range 1e5-1e7 Pa/m"),
    "friction": lognormal_median(
        0.09, math.log(FRICTION_SPAN[1] / FRICTION_SPAN[0]) / (2.0 * float(ndtri(0.95))),
        unit="",
        source="median 0.09 (Watanabe et al., Commun Eng 2024); spread U, 5th-95th "
               "percentiles a factor 7.7 apart as 0.007-0.054 (Lyle et al. 2013); truncated "
               "to its 1st-99th percentiles"),
}
"""Each tissue figure of the wall (the compliant wall's field of that name) across patients;
module docstring."""

STIFFNESS = ("thickness", "circumferential_modulus", "support_stiffness")
"""The figures that make the wall stiff (high) or soft (low) together."""
GRIP = ("friction",)
"""The figure that makes it sticky (high) or slippery (low)."""

LOW, MIDDLE, HIGH = 5.0, 50.0, 95.0
"""The percentiles of a named corner: an extreme at the 5th or the 95th, the other side at
the median."""
CORNERS = {
    "soft": (LOW, MIDDLE), "stiff": (HIGH, MIDDLE),
    "slippery": (MIDDLE, LOW), "sticky": (MIDDLE, HIGH),
    "soft_slippery": (LOW, LOW), "soft_sticky": (LOW, HIGH),
    "stiff_slippery": (HIGH, LOW), "stiff_sticky": (HIGH, HIGH),
}
"""The named corners: (percentile of each STIFFNESS figure, percentile of each GRIP figure).
soft_sticky is the wall a capsule sinks into and grips (the hardest to drag along);
stiff_slippery the easiest."""

DRAWN, NOMINAL = "drawn", "nominal"
TISSUE_CHOICES = (DRAWN, NOMINAL) + tuple(CORNERS)
"""What `colon.source.tissue` may be: drawn for the patient (the default), the scenario's
contact figures as given (nominal), or a named corner."""


@dataclasses.dataclass(frozen=True)
class PatientTissue:
    """One patient's wall: how it was chosen ("drawn", a corner's name, "percentile 30" or
    "nominal"), the figures (SPREADS' names, SI units) and the percentile (0-100) each lies
    at (empty for nominal)."""

    how: str
    values: dict
    percentiles: dict


def check_tissue_request(tissue: str, percentile, where: str = "colon.source") -> None:
    """Raises ValueError (one line, naming the key) for a tissue request that is not one."""
    if tissue not in TISSUE_CHOICES:
        raise ValueError(f"{where}.tissue must be one of {', '.join(TISSUE_CHOICES)}, "
                         f"got {tissue!r}")
    if percentile is None:
        return
    need_range(percentile, f"{where}.tissue_percentile", "(0, 100)", "", "or null: drawn")
    if tissue != DRAWN:
        raise ValueError(f"{where}.tissue_percentile sets every figure of the wall in place "
                         f"of the draw: only with tissue: {DRAWN}, not with tissue: {tissue}")


def patient_tissue(seed: int, tissue: str = DRAWN, percentile=None) -> PatientTissue:
    """The wall of the population's patient `seed` for a tissue request (`tissue`, and
    `percentile` for every figure at once): the figures drawn from the patient's stream,
    or at the corner's or the given percentiles. For "nominal", no figures."""
    check_tissue_request(tissue, percentile)
    if tissue == NOMINAL:
        return PatientTissue(NOMINAL, {}, {})
    if tissue in CORNERS:
        stiff, grip = CORNERS[tissue]
        how = tissue
        q = {name: (stiff if name in STIFFNESS else grip) / 100.0 for name in SPREADS}
    elif percentile is not None:
        how = f"percentile {percentile:g}"
        q = dict.fromkeys(SPREADS, percentile / 100.0)
    else:
        how = DRAWN
        rng = np.random.default_rng([int(seed), TISSUE_STREAM])
        q = {name: float(rng.uniform()) for name in SPREADS}   # SPREADS' order, one each
    return PatientTissue(how, {name: SPREADS[name].quantile(q[name]) for name in SPREADS},
                         {name: 100.0 * q[name] for name in SPREADS})


def has_tissue(config) -> bool:
    """Whether a contact model's config has the wall's tissue figures (the compliant wall
    does; the rigid stand-in does not)."""
    return dataclasses.is_dataclass(config) and set(SPREADS) <= {
        f.name for f in dataclasses.fields(config)}


def _request(colon_params):
    """The population's tissue request of `colon_params`, or None (not from the
    population)."""
    population = getattr(colon_params, "population", None)
    if population is None:
        return None
    return population.tissue, population.tissue_percentile


def wall_tissue(config, colon_params) -> PatientTissue | None:
    """The tissue the contact `config` has for the patient of `colon_params`: the patient's
    (`patient_tissue`) for a colon from the population, "nominal" (the config's own figures)
    otherwise; None for a contact model without tissue figures."""
    if not has_tissue(config):
        return None
    request = _request(colon_params)
    tissue = (PatientTissue(NOMINAL, {}, {}) if request is None
              else patient_tissue(colon_params.seed, *request))
    if tissue.how == NOMINAL:
        return PatientTissue(NOMINAL, {name: getattr(config, name) for name in SPREADS}, {})
    return tissue


def patient_wall(config, colon_params):
    """The contact `config` with the patient's wall: a `dataclasses.replace` of it with the
    figures of `patient_tissue` for a colon from the population (`colon_params.population`),
    the other fields the config's; `config` itself for any other colon, for tissue: nominal,
    and for a contact model without tissue figures (the rigid stand-in). Deterministic, and
    the same whether applied once or twice."""
    tissue = wall_tissue(config, colon_params)
    if tissue is None or tissue.how == NOMINAL:
        return config
    return dataclasses.replace(config, **tissue.values)


TISSUE_COLUMNS = ("tissue", "tissue_thickness_mm", "tissue_modulus_MPa",
                  "tissue_support_MPa_per_m", "tissue_friction")
"""The tissue a run's contact had, as metrics.json and the benchmark's table give it."""

TISSUE_COLUMN_DOCS = {
    "tissue": "how the run's wall was chosen (`tissue_metrics`): \"drawn\" for the patient, "
              "a corner's name (\"soft\", \"stiff_sticky\", ...), \"percentile P\", "
              "\"nominal\" (the scenario's contact figures), or \"none (rigid stand-in)\" "
              "for a contact model without tissue figures (text)",
    "tissue_thickness_mm": "the thickness of the run's wall (the patient's; "
                           "contact.thickness when nominal); NaN on the rigid stand-in (mm)",
    "tissue_modulus_MPa": "the circumferential tensile modulus of the run's wall "
                          "(contact.circumferential_modulus when nominal); NaN on the rigid "
                          "stand-in (MPa)",
    "tissue_support_MPa_per_m": "the elastic support outside the run's wall "
                                "(contact.support_stiffness when nominal); NaN on the rigid "
                                "stand-in (MPa/m)",
    "tissue_friction": "Coulomb friction between capsule and mucosa (contact.friction "
                       "when nominal); NaN on the rigid stand-in (1)",
}
"""What each of TISSUE_COLUMNS is, ending in its unit in parentheses (the benchmark's
COLUMN_DOCS, app/benchmark/task.py, take them)."""


def tissue_metrics(config, colon_params) -> dict:
    """What the run's wall was (TISSUE_COLUMNS and `tissue_percentiles`): how it was chosen
    ("drawn", a corner, "percentile 30", "nominal"; "none (rigid stand-in)" for a contact
    model without tissue figures, whose figures are then null), the thickness (mm), the
    circumferential modulus (MPa), the support (MPa/m), the friction, and the percentile of
    each among the population's patients (null for nominal figures)."""
    tissue = wall_tissue(config, colon_params)
    if tissue is None:
        return {"tissue": "none (rigid stand-in)", **dict.fromkeys(TISSUE_COLUMNS[1:]),
                "tissue_percentiles": None}
    v = tissue.values
    return {"tissue": tissue.how,
            "tissue_thickness_mm": round(1e3 * v["thickness"], 4),
            "tissue_modulus_MPa": round(1e-6 * v["circumferential_modulus"], 5),
            "tissue_support_MPa_per_m": round(1e-6 * v["support_stiffness"], 5),
            "tissue_friction": round(v["friction"], 5),
            "tissue_percentiles": ({name: round(p, 2) for name, p in tissue.percentiles.items()}
                                   if tissue.percentiles else None)}
