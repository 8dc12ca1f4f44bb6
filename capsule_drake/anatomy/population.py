"""Patients drawn from the population: a colon's segment lengths and diameters sampled from
published statistics, for a seed, a sex, a bowel habit, a length percentile or a variant.

`sample_patient(request)` returns the segments' lengths and diameters of one patient
(`Patient`); `resolve_population(params)` writes them into a `ColonParams`, whose
procedural course (anatomy/course.py) then follows them. Sources and their status
(docs/sources.md section 3.2):

- Total length (anus to cecal pole, CT colonography centreline, n = 295): 150.3 +- 18.5 cm,
  109.7-195.9; women 154.3 +- 18.1, men 147.1 +- 18.3; bowel habit daily 147.4 +- 17.9,
  every 2-3 days 154.7 +- 18.5, less often 158.6 +- 18.3 (Utano et al. 2022, V). The extra
  length of women and of constipated patients lies in the proximal colon (V).
- How the length divides into segments: sigmoid 48.7 and transverse 49.2 cm in colons of
  167 cm mean total (Hanson et al., AJR 2007, V); the median transverse colon 48 cm in women
  and 40 cm in men (Saunders et al. 1996, V); rectosigmoid 44.0 +- 11.6 cm (Madiba et al.
  2008, V) and sigmoid 35.5 +- 12.1 cm (Ran et al. 2012, V): a sigmoid SD of ~12 cm. The
  other segments' shares are the textbook lengths' (U).
- Redundant sigmoid: 24-25 % of White and Indian patients (Madiba et al. 2008, V): here the
  longest 24 % of sigmoids.

What no source at hand gives, and is assumed (U): that sex and bowel habit add their
effects on the mean; the log-normal spread of each segment's share (SHARE_SPREAD, set for
the sigmoid's SD of ~12 cm); the diameters' spread. The course's shortest sigmoid is
~23 cm: one drawn shorter (about 3 %) is built at that length (COURSE_REACH allows 20 cm).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_dump_typed
from scipy.optimize import fsolve
from scipy.stats import norm, truncnorm

from .abdomen import Abdomen
from .cache import CacheError, default_cache_root, params_hash, write_atomic
from .course import nominal_radius, solve_course
from .morphology import acute_flexures
from .params import (DIAMETER_RANGE, SEGMENT_NAMES, ColonParams, Population,
                     check_population_params)
from .tortuosity import add_flexures

# Utano et al. 2022 (V): total length (cm), mean and SD, overall, by sex, by bowel habit.
LENGTH_ALL = (150.3, 18.5)
LENGTH_BY_SEX = {"female": (154.3, 18.1), "male": (147.1, 18.3)}
LENGTH_BY_HABIT = {"daily": (147.4, 17.9), "every_2_3_days": (154.7, 18.5),
                   "less_often": (158.6, 18.3)}
LENGTH_RANGE = (109.7, 195.9)
FEMALE_SHARE = (LENGTH_ALL[0] - LENGTH_BY_SEX["male"][0]) / (
    LENGTH_BY_SEX["female"][0] - LENGTH_BY_SEX["male"][0])
"""Share of women that makes the sexes' means average to the overall one (0.44: derived
from Utano's means; the cohort's own split is not in the abstract)."""

# Mean share of each segment in the total length. Sigmoid and transverse from Hanson 2007
# (48.7 and 49.2 of 167 cm, V); rectum, descending, ascending and cecum from the textbook
# lengths (13.5, 25, 17.5, 7 of 150 cm, U), the whole normalised to 1.
_RAW_SHARES = {"rectum": 13.5 / 150.0, "sigmoid": 48.7 / 167.0, "descending": 25.0 / 150.0,
               "transverse": 49.2 / 167.0, "ascending": 17.5 / 150.0, "cecum": 7.0 / 150.0}
MEAN_SHARES = {name: share / sum(_RAW_SHARES.values()) for name, share in _RAW_SHARES.items()}
TRANSVERSE_BY_SEX = {"female": 48.0, "male": 40.0}
"""Median transverse length (cm), Saunders et al. 1996 (V): the transverse share is scaled
by sex around its mean so that women's is 48 / 40 of men's."""
SHARE_SPREAD = {"rectum": 0.10, "sigmoid": 0.30, "descending": 0.12, "transverse": 0.18,
                "ascending": 0.15, "cecum": 0.12}
"""Relative spread (log-normal sigma) of each segment's share before the shares are
normalised (U): the sigmoid and the transverse colon vary most (rectosigmoid length explains
most of the total's variation, Phillips et al. 2015, V), and with the total's spread the
sigmoid's SD is ~12 cm, as the rectosigmoid and sigmoid series report (11.6-12.2 cm)."""
REDUNDANT_SIGMOID_SHARE = 0.24
"""Share of patients with a redundant sigmoid (Madiba et al. 2008, V: 24 % and 25 %)."""
DIAMETER_SPREAD = 0.08
"""Relative SD of each segment's distended diameter around the procedural default (U:
the sigmoid's widest point is 40 +- 7 mm, an SD of 18 %, Chung et al. 2006; the averaged
diameter varies less)."""

# Acute-angle flexures (anatomy/morphology.py). Khashab et al. 2009 (V): 10.9 +- 2.4 per
# colon (n = 505) in colons 189.5 +- 26.3 cm long by their centreline; Hanson et al. 2007
# (V): 9.6 in colons of 167 cm (completed colonoscopies) and 11.9 in colons of 210.8 cm
# (failed ones). The three groups have 5.65-5.75 flexures per metre of their own length; the
# lengths here are Utano's (150.3 cm), from another centreline and another population. What
# carries over is the count per metre: a patient's flexures are drawn as Khashab's 5.75 per
# metre of the patient's length, with Khashab's relative spread (22 %, U: that the spread
# scales with the mean).
FLEXURES_KHASHAB = (10.9, 2.4, 189.5)    # mean, SD, mean length (cm)
FLEXURES_PER_METRE = FLEXURES_KHASHAB[0] / (FLEXURES_KHASHAB[2] / 100.0)
FLEXURES_HANSON = {"completed": (9.6, 167.0), "failed": (11.9, 210.8)}


def flexure_distribution() -> tuple[float, float, float]:
    """(mean, SD, SD of the part not explained by length) of the flexure count of the
    population's patients (before rounding): FLEXURES_PER_METRE x the length, spread to
    Khashab's coefficient of variation."""
    mean = FLEXURES_PER_METRE * LENGTH_ALL[0] / 100.0
    sd = FLEXURES_KHASHAB[1] / FLEXURES_KHASHAB[0] * mean
    from_length = FLEXURES_PER_METRE * LENGTH_ALL[1] / 100.0
    return mean, sd, float(np.sqrt(max(sd**2 - from_length**2 - 1.0 / 12.0, 0.0)))


# The course (anatomy/course.py) has room for these segment lengths (m): what its shape
# brackets reach, less a margin. A sampled length beyond them is a patient the course
# cannot draw: redrawn, and counted (Patient.redraws).
COURSE_REACH = {"rectum": (0.08, 0.165), "sigmoid": (0.20, 0.80),
                "descending": (0.12, 0.35), "transverse": (0.33, 0.80),
                "ascending": (0.085, 0.27), "cecum": (0.025, 0.115)}
_MAX_REDRAWS = 200


@dataclass
class Patient:
    """One sampled patient."""

    sex: str
    total_length: float                    # m, the sum of the segments
    lengths: dict[str, float]              # m, per segment (SEGMENT_NAMES)
    diameters: dict[str, float]            # m, per segment
    redundant_sigmoid: bool
    redraws: int                           # draws the course had no room for
    flexures: int = 0                      # acute-angle flexures drawn for the patient
    flexures_built: int | None = None      # ... and those its course has (resolve_population)


def length_distribution(sex: str, habit: str) -> tuple[float, float]:
    """Mean and SD (cm) of the total length for a sex and a bowel habit ("any" for either):
    the group's published figures; both given, the sex's mean shifted by the habit's
    difference from the whole cohort's (additive effects: an assumption)."""
    if sex != "any" and habit != "any":
        mean = LENGTH_BY_SEX[sex][0] + LENGTH_BY_HABIT[habit][0] - LENGTH_ALL[0]
        return mean, 0.5 * (LENGTH_BY_SEX[sex][1] + LENGTH_BY_HABIT[habit][1])
    if sex != "any":
        return LENGTH_BY_SEX[sex]
    if habit != "any":
        return LENGTH_BY_HABIT[habit]
    return LENGTH_ALL


@functools.lru_cache(maxsize=64)
def _parent_normal(mean: float, sd: float, low: float, high: float) -> tuple[float, float]:
    """The normal whose truncation to [low, high] has `mean` and `sd`: a published sample's
    mean and SD are those of its truncated range, so the parent is wider."""
    def moments(x):
        mu, sigma = x[0], abs(x[1])
        a, b = (low - mu) / sigma, (high - mu) / sigma
        m, v = truncnorm.stats(a, b, loc=mu, scale=sigma, moments="mv")
        return [float(m) - mean, float(np.sqrt(v)) - sd]
    mu, sigma = fsolve(moments, [mean, sd], xtol=1e-10)
    return float(mu), float(abs(sigma))


def _truncated_normal_quantile(q: float, mean: float, sd: float, low: float,
                               high: float) -> float:
    """The q-quantile of the distribution on [low, high] with `mean` and `sd` (a truncated
    normal)."""
    mu, sigma = _parent_normal(mean, sd, low, high)
    a, b = norm.cdf((low - mu) / sigma), norm.cdf((high - mu) / sigma)
    return float(mu + sigma * norm.ppf(a + q * (b - a)))


def _sigmoid_threshold(sex: str) -> float:
    """Sigmoid length (m) above which a sigmoid counts as redundant: the population's
    (1 - REDUNDANT_SIGMOID_SHARE) quantile for the sex, by a fixed-seed sample."""
    rng = np.random.default_rng(20090801)
    values = []
    for _ in range(4000):
        draw_sex = sex if sex != "any" else ("female" if rng.uniform() < FEMALE_SHARE
                                             else "male")
        total = _draw_total(rng, draw_sex, "any", None)
        values.append(_draw_segments(rng, draw_sex, total)["sigmoid"])
    return float(np.quantile(values, 1.0 - REDUNDANT_SIGMOID_SHARE))


_THRESHOLDS: dict[str, float] = {}


def _draw_total(rng, sex: str, habit: str, percentile) -> float:
    """The total length (m): the group's truncated normal, at `percentile` if given."""
    mean, sd = length_distribution(sex, habit)
    q = rng.uniform() if percentile is None else percentile / 100.0
    return _truncated_normal_quantile(q, mean, sd, *LENGTH_RANGE) / 100.0


def _draw_segments(rng, sex: str, total: float) -> dict[str, float]:
    """The segments' lengths (m) of a colon `total` long: the mean shares (the transverse
    colon's by sex), each spread log-normally by SHARE_SPREAD, normalised to the total."""
    shares = dict(MEAN_SHARES)
    if sex != "any":   # women's transverse 48 / 40 of men's, around the mean share
        shares["transverse"] *= TRANSVERSE_BY_SEX[sex] / np.mean(list(TRANSVERSE_BY_SEX.values()))
    drawn = np.array([shares[n] * np.exp(SHARE_SPREAD[n] * rng.normal() - 0.5 * SHARE_SPREAD[n] ** 2)
                      for n in SEGMENT_NAMES])
    drawn *= total / drawn.sum()
    return {name: float(length) for name, length in zip(SEGMENT_NAMES, drawn)}


def _fits(lengths: dict[str, float]) -> bool:
    return all(COURSE_REACH[n][0] <= lengths[n] <= COURSE_REACH[n][1] for n in SEGMENT_NAMES)


def sample_patient(params: Population, seed: int, attempt: int = 0) -> Patient:
    """The patient of `seed` with `params`' fixed traits (its own stream: [seed, 7], and
    [seed, 7, attempt] for the later attempts of `population_colon_params`).

    The total length follows its published distribution exactly: a draw whose segments the
    course cannot draw redraws the segments only; a variant asked for (`sigmoid`) redraws
    the total too (a redundant sigmoid comes with a longer colon), unless the length's
    percentile is fixed."""
    check_population_params(params)
    rng = np.random.default_rng([seed, 7] if attempt == 0 else [seed, 7, attempt])
    sex = params.sex if params.sex != "any" else (
        "female" if rng.uniform() < FEMALE_SHARE else "male")
    if sex not in _THRESHOLDS:
        _THRESHOLDS[sex] = _sigmoid_threshold(sex)
    threshold = _THRESHOLDS[sex]
    total = _draw_total(rng, sex, params.bowel_habit, params.length_percentile)
    for redraws in range(_MAX_REDRAWS):
        lengths = _draw_segments(rng, sex, total)
        redundant = lengths["sigmoid"] > threshold
        wanted = {"any": True, "redundant": redundant, "normal": not redundant}[params.sigmoid]
        if wanted and _fits(lengths):
            break
        if not wanted and params.length_percentile is None:
            total = _draw_total(rng, sex, params.bowel_habit, None)
    else:
        raise ValueError(f"colon.source: no patient of seed {seed} with these traits "
                         f"(sex {params.sex}, bowel_habit {params.bowel_habit}, "
                         f"length_percentile {params.length_percentile}, sigmoid "
                         f"{params.sigmoid}) fits the procedural course in {_MAX_REDRAWS} draws")
    defaults = ColonParams()
    diameters = {}
    for name in SEGMENT_NAMES:
        nominal = defaults.segment(name).diameter
        low, high = DIAMETER_RANGE[name]
        diameters[name] = float(np.clip(nominal * np.clip(1.0 + DIAMETER_SPREAD * rng.normal(),
                                                          0.75, 1.25), low, high))
    total = float(sum(lengths.values()))
    flexures = int(round(FLEXURES_PER_METRE * total
                         + flexure_distribution()[2] * rng.normal()))
    return Patient(sex=sex, total_length=total, lengths=lengths, diameters=diameters,
                   redundant_sigmoid=bool(redundant), redraws=redraws,
                   flexures=max(flexures, 0))


COURSE_ATTEMPTS = 20
"""Patients drawn, in turn, until the procedural course can draw one without kinks or
overlaps (`resolve_population`): about 1 in 10 cannot (short sigmoids with long rectums,
wide ceca), so the population the course draws is a little narrower than the one sampled
(measured over 80 seeds: 8 redrawn, totals 147.6 +- 17.8 -> 148.2 +- 17.9 cm;
docs/models/colon.md, "Patients from the population")."""

_RESOLVED: dict[str, tuple] = {}
_PATIENTS: dict[str, Patient] = {}
_KEEP_RESOLVED = 16


def resolve_population(params: ColonParams, bend: bool = True) -> tuple[ColonParams, tuple]:
    """(`params` with the segments of the patient of `params.seed` drawn from
    `params.population`: each segment's length fixed, length_min = length_max, and its
    diameter; the course solved for them, as `solve_course` returns it). A patient the
    procedural course cannot draw is replaced by the seed's next draw. Once per process for
    equal parameters: the scenario's check and the colon's build ask for the same patient.
    With `bend` False the course is not bent to the patient's flexures (seconds to minutes,
    `bend_course`): what the scenario's check and the patient's label need; the patient is
    the same unless no placement of its flexures passes the course's checks, then the next
    draw's. The wall's tissue asked of the population is not the colon's shape: patients
    differing only in it are resolved once (`shape_params`)."""
    key = _resolved_key(params, bend)
    if key in _RESOLVED:
        out, course = _RESOLVED[key]
        if out.source != params.source:   # the same colon, another wall asked for
            out = dataclasses.replace(out, source=params.source)
        return out, course
    stored = _course_file(params)
    for attempt in range(COURSE_ATTEMPTS):
        patient = sample_patient(params.population, params.seed, attempt)
        out = dataclasses.replace(params)
        for name in SEGMENT_NAMES:
            setattr(out, name, dataclasses.replace(
                params.segment(name), length_min=patient.lengths[name],
                length_max=patient.lengths[name], diameter=patient.diameters[name]))
        found = _read_course(stored, attempt) if bend else None
        if found is None:
            try:
                course = solve_course(out, np.random.default_rng(out.seed))
            except RuntimeError:
                continue
            if not bend:
                found = (course, len(acute_flexures(*course[:2])))
            else:
                found = bend_course(out, course, patient.flexures)
                if found is None:
                    continue
                _write_course(stored, attempt, *found)
        course, built = found
        patient = dataclasses.replace(patient, flexures_built=built if bend else None)
        if len(_RESOLVED) >= _KEEP_RESOLVED:
            _PATIENTS.pop(next(iter(_RESOLVED)), None)
            _RESOLVED.pop(next(iter(_RESOLVED)))
        _RESOLVED[key] = (out, course)
        _PATIENTS[key] = patient
        return out, course
    raise ValueError(f"colon.source: the procedural course cannot draw any of the first "
                     f"{COURSE_ATTEMPTS} patients of seed {params.seed} with these traits")


def _resolved_key(params: ColonParams, bend: bool) -> str:
    """What `resolve_population` keeps its patients by: the colon's shape, and `bend`."""
    return yaml_dump_typed(shape_params(params)) + f"\nbend: {bend}"


def _course_file(params: ColonParams) -> Path:
    """Where the resolved course of `params` is kept between processes (seconds to a few
    minutes to bend; keyed like the colon's files, by parameters and source)."""
    key = params_hash(shape_params(params))
    return default_cache_root().parent / "population" / f"{key}.npz"


_TISSUE_FIELDS = ("tissue", "tissue_percentile")
"""The population's fields that say what the wall is made of, not where it lies."""


def shape_params(params: ColonParams) -> ColonParams:
    """`params` with the population's tissue request (`tissue`, `tissue_percentile`: the
    wall's mechanics, physics/contact/tissue.py) at its defaults: what the colon's shape
    depends on, the key of its cached course and files (a patient asked for with another
    wall is the same colon)."""
    population = params.population
    if population is None:
        return params
    defaults = Population()
    return dataclasses.replace(params, source=dataclasses.replace(
        population, **{name: getattr(defaults, name) for name in _TISSUE_FIELDS}))


def _read_course(path: Path, attempt: int):
    """((s, points, boundaries, targets), flexures) kept for `attempt`, or None."""
    if not path.exists():
        return None
    with np.load(path) as data:
        if int(data["attempt"]) != attempt:
            return None
        targets = {str(n): float(v) for n, v in zip(data["target_names"],
                                                     data["target_lengths"])}
        return ((data["s"], data["points"], data["boundaries"], targets),
                int(data["flexures"]))


def _write_course(path: Path, attempt: int, course: tuple, flexures: int) -> None:
    s, points, boundaries, targets = course
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(targets)

    def write(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, attempt=attempt, flexures=flexures, s=s, points=points,
                     boundaries=boundaries, target_names=np.array(names),
                     target_lengths=np.array([targets[n] for n in names]))
    try:
        write_atomic(path, write)
    except (OSError, CacheError):
        pass   # a read-only or full cache: the course is solved again next time


BEND_ATTEMPTS = 4
"""Placements of a patient's added flexures tried in turn (`bend_course`)."""
MOBILE_ODDS = 3.0
"""How much likelier an added flexure is in the sigmoid or the transverse colon, which hang
on their mesenteries, than in the fixed segments (U: where CT colonography finds them is
not in the abstracts at hand)."""


def bend_course(params: ColonParams, course: tuple, flexures: int):
    """((s, points, boundaries, targets), flexures it has) of the solved `course` bent to
    `flexures` acute-angle flexures (anatomy/tortuosity.py): new ones between the rectum's
    first 8 cm and the ascending colon's last 6 cm (the cecum is too wide to turn within
    10 cm), each placement drawn from the stream [seed, 12, attempt]. The first placement
    that makes the count is taken, else the closest; None when no placement passes the
    course's checks."""
    s, points, boundaries, targets = course
    existing = len(acute_flexures(s, points))
    flexures = max(flexures, existing)
    if flexures == existing:
        return course, existing
    abdomen = Abdomen(params.abdomen)

    def radius_of(q, b):
        return nominal_radius(q, b, params)

    def allowed(q):
        return (q > 0.08) & (q < boundaries[5] - 0.06)

    def weight(q):   # the mobile sigmoid and transverse colon MOBILE_ODDS times as likely
        segment = np.searchsorted(boundaries, q, side="right") - 1
        return np.where(np.isin(segment, [1, 3]), MOBILE_ODDS, 1.0)

    best = None
    for attempt in range(BEND_ATTEMPTS):
        out = add_flexures(s, points, boundaries, radius_of, abdomen, flexures,
                           np.random.default_rng([params.seed, 12, attempt]), allowed,
                           params.centerline_step, weight)
        if out is None:
            continue
        if best is None or abs(out[3] - flexures) < abs(best[3] - flexures):
            best = out
        if best[3] == flexures:
            break
    if best is None:
        return None
    return (best[0], best[1], best[2], targets), best[3]


def resolved_patient(params: ColonParams, bend: bool = True) -> Patient:
    """The patient `resolve_population(params, bend)` draws (the attempt the course could
    draw)."""
    resolve_population(params, bend)
    return _PATIENTS[_resolved_key(params, bend)]


def patient_label(params: ColonParams) -> str:
    """The patient's sex and sigmoid variant ("female, redundant sigmoid"), or "" for a
    colon not drawn from the population."""
    if params.population is None:
        return ""
    patient = resolved_patient(params, bend=False)
    return f"{patient.sex}, {'redundant' if patient.redundant_sigmoid else 'normal'} sigmoid"


def population_colon_params(params: ColonParams, population: Population) -> ColonParams:
    """`params` with the patient of `params.seed` drawn from `population`
    (`resolve_population`)."""
    return resolve_population(dataclasses.replace(params, source=population))[0]
