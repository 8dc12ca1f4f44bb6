"""Patients drawn from the population (anatomy/population.py) against the published
statistics they are drawn from (docs/sources.md section 3.2)."""

import dataclasses

import numpy as np
import pytest

from capsule_drake.anatomy import ColonParams, SEGMENT_NAMES, build_colon
from capsule_drake.anatomy.course import solve_course
from capsule_drake.anatomy.morphology import acute_flexures
from capsule_drake.anatomy.params import Population
from capsule_drake.anatomy.population import (FLEXURES_HANSON, FLEXURES_KHASHAB,
                                              FLEXURES_PER_METRE, LENGTH_ALL,
                                              LENGTH_BY_HABIT, LENGTH_BY_SEX, LENGTH_RANGE,
                                              REDUNDANT_SIGMOID_SHARE,
                                              flexure_distribution, population_colon_params,
                                              resolve_population, resolved_patient,
                                              sample_patient)
from capsule_drake.scenario import ScenarioError, load_scenario

N = 500
COHORT = 295   # Utano et al. 2022


def totals_cm(request, n=N, first_seed=0):
    return np.array([sample_patient(request, seed).total_length
                     for seed in range(first_seed, first_seed + n)]) * 100.0


def within_published(values, mean, sd, n_published):
    """The sample's mean and SD each within twice the combined standard error of the
    published figure (n_published patients) and of this sample."""
    n = len(values)
    se_mean = np.hypot(sd / np.sqrt(n_published), sd / np.sqrt(n))
    se_sd = np.hypot(sd / np.sqrt(2 * (n_published - 1)), sd / np.sqrt(2 * (n - 1)))
    assert abs(values.mean() - mean) < 2 * se_mean, (values.mean(), mean, 2 * se_mean)
    assert abs(values.std(ddof=1) - sd) < 2 * se_sd, (values.std(ddof=1), sd, 2 * se_sd)


def test_500_patients_have_the_published_length_mean_sd_and_range():
    """150.3 +- 18.5 cm, 109.7-195.9 (CT colonography, n = 295)."""
    totals = totals_cm(Population())
    within_published(totals, *LENGTH_ALL, COHORT)
    assert LENGTH_RANGE[0] <= totals.min() and totals.max() <= LENGTH_RANGE[1]
    # A new sample (other seeds) agrees too: the figures are not those of one draw.
    within_published(totals_cm(Population(), first_seed=10_000), *LENGTH_ALL, COHORT)


@pytest.mark.parametrize("sex", ["female", "male"])
def test_each_sex_has_its_published_length(sex):
    """Women 154.3 +- 18.1, men 147.1 +- 18.3 cm; drawn as "any", 44 % are women."""
    within_published(totals_cm(Population(sex=sex)), *LENGTH_BY_SEX[sex], COHORT // 2)


@pytest.mark.parametrize("habit", sorted(LENGTH_BY_HABIT))
def test_each_bowel_habit_has_its_published_length(habit):
    """Daily 147.4 +- 17.9, every 2-3 days 154.7 +- 18.5, less often 158.6 +- 18.3 cm
    (the group sizes are not in the abstract: a third of the cohort each, assumed)."""
    within_published(totals_cm(Population(bowel_habit=habit)),
                     *LENGTH_BY_HABIT[habit], COHORT // 3)


def test_segments_the_redundant_sigmoid_and_the_transverse_by_sex():
    """The segments sum to the total; the sigmoid's SD is that of the sigmoid series
    (11.6-12.2 cm: 10-14 allowed); a quarter of sigmoids are redundant (24 %, +- twice the
    binomial SE); women's transverse colon is longer than men's (medians 48 and 40 cm:
    ratio 1.1-1.3)."""
    patients = [sample_patient(Population(), seed) for seed in range(N)]
    for p in patients:
        assert sum(p.lengths.values()) == pytest.approx(p.total_length, rel=1e-12)
        assert list(p.lengths) == list(SEGMENT_NAMES)
    sigmoid = np.array([p.lengths["sigmoid"] for p in patients]) * 100
    assert 10.0 < sigmoid.std() < 14.0
    redundant = np.mean([p.redundant_sigmoid for p in patients])
    se = np.sqrt(REDUNDANT_SIGMOID_SHARE * (1 - REDUNDANT_SIGMOID_SHARE) / N)
    assert abs(redundant - REDUNDANT_SIGMOID_SHARE) < 2.5 * se
    transverse = {sex: np.median([p.lengths["transverse"] for p in patients if p.sex == sex])
                  for sex in ("female", "male")}
    assert 1.1 < transverse["female"] / transverse["male"] < 1.3
    women = np.mean([p.sex == "female" for p in patients])
    assert abs(women - 0.444) < 0.07


def test_a_percentile_and_a_variant_are_what_was_asked():
    """A 95th-percentile woman is 154.3 + 1.645 x 18.1 = 184 cm long, whatever the seed (to
    the truncation's shift); a redundant sigmoid is redundant; a normal one is not."""
    tall = [sample_patient(Population(sex="female", length_percentile=95), seed)
            for seed in range(20)]
    assert all(abs(p.total_length * 100 - 184.1) < 1.5 for p in tall)
    assert len({round(p.total_length, 9) for p in tall}) == 1
    assert all(sample_patient(Population(sigmoid="redundant"), s).redundant_sigmoid
               for s in range(20))
    assert not any(sample_patient(Population(sigmoid="normal"), s).redundant_sigmoid
                   for s in range(20))
    assert sample_patient(Population(), 7) == sample_patient(Population(), 7)


@pytest.mark.parametrize("text, key", [
    ("{colon: {source: !Population {sex: other}}}", "colon.source.sex"),
    ("{colon: {source: !Population {length_percentile: 100}}}",
     "colon.source.length_percentile"),
    ("{colon: {source: !Population {sigmoid: twisted}}}", "colon.source.sigmoid"),
    ("{colon: {source: !Population {bowel_habit: weekly}}}", "colon.source.bowel_habit"),
    ("{colon: {source: !Population {sex: female, habit: daily}}}", "colon.source.habit"),
])
def test_an_impossible_request_is_one_line_at_load(text, key):
    with pytest.raises(ScenarioError) as error:
        load_scenario(override=text)
    message = str(error.value)
    assert key in message and "\n" not in message


@pytest.mark.slow
def test_drawn_patients_are_built_with_their_segments():
    """Seven patients built: each segment of the course as long as drawn (to 1 mm), the
    diameters the patient's, and a redundant 95th-percentile patient among them."""
    for seed in range(5):
        params = population_colon_params(ColonParams(seed=seed), Population())
        s, _, boundaries, targets = solve_course(params, np.random.default_rng(seed))
        np.testing.assert_allclose(np.diff(boundaries),
                                   [targets[name] for name in SEGMENT_NAMES], atol=1e-3)
    tall = dataclasses.replace(ColonParams(seed=3), source=Population(
        sex="female", length_percentile=95, sigmoid="redundant"))
    colon = build_colon(tall)
    assert colon.centerline.s[-1] == pytest.approx(1.84, abs=0.01)
    assert colon.params.sigmoid.length_min > 0.45
    standard = build_colon(ColonParams(seed=3))
    assert standard.centerline.s[-1] < 1.6


def _polyline(pieces, step=0.001):
    """A planar centreline of straight runs and circular arcs: pieces of ("line", length)
    and ("arc", radius, degrees, +1 left / -1 right); returns (s, points)."""
    points, heading, p = [np.zeros(3)], 0.0, np.zeros(3)
    for piece in pieces:
        if piece[0] == "line":
            n = int(round(piece[1] / step))
            for _ in range(n):
                p = p + step * np.array([np.cos(heading), np.sin(heading), 0.0])
                points.append(p)
        else:
            _, radius, degrees, side = piece
            n = int(round(radius * np.radians(degrees) / step))
            for _ in range(n):
                heading += side * step / radius
                p = p + step * np.array([np.cos(heading), np.sin(heading), 0.0])
                points.append(p)
    points = np.array(points)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    return s, points


def test_acute_flexures_are_the_turns_beyond_90_degrees_within_10_cm():
    """Known shapes: three hairpins (180 degrees on a 3 cm radius) between straight runs are
    three flexures at their apices; a 100-degree corner on a 2 cm radius is one; a
    60-degree corner, and a gentle 40 cm radius turning 120 degrees, none."""
    hairpins = [("line", 0.2)]
    for k in range(3):
        hairpins += [("arc", 0.03, 180.0, 1 if k % 2 == 0 else -1), ("line", 0.15)]
    s, points = _polyline(hairpins)
    found = acute_flexures(s, points)
    assert len(found) == 3
    apex = [0.2 + 0.5 * np.pi * 0.03 + k * (np.pi * 0.03 + 0.15) for k in range(3)]
    np.testing.assert_allclose(found, apex, atol=0.004)
    assert len(acute_flexures(*_polyline([("line", 0.2), ("arc", 0.02, 100.0, 1),
                                          ("line", 0.2)]))) == 1
    assert len(acute_flexures(*_polyline([("line", 0.2), ("arc", 0.02, 60.0, 1),
                                          ("line", 0.2)]))) == 0
    assert len(acute_flexures(*_polyline([("line", 0.1), ("arc", 0.40, 120.0, -1),
                                          ("line", 0.1)]))) == 0


def test_500_patients_have_the_published_flexures_per_metre():
    """Drawn flexure counts: Khashab's 10.9 +- 2.4 in colons of 189.5 cm and Hanson's 9.6 in
    167 cm and 11.9 in 210.8 cm are 5.65-5.75 per metre; the patients here (Utano's lengths)
    have 5.75 per metre of their own length, so 8.65 +- 1.90 flexures (Khashab's 22 %
    spread): the mean and SD each within twice the combined standard error of Khashab's
    505 patients (scaled) and these 500; longer colons have more (Hanson's groups: 2.3 more
    in colons 44 cm longer; here the count's slope on length, per metre, within 20 % of
    the 5.75)."""
    patients = [sample_patient(Population(), seed) for seed in range(N)]
    counts = np.array([p.flexures for p in patients], dtype=float)
    lengths = np.array([p.total_length for p in patients])
    mean, sd, _ = flexure_distribution()
    assert mean == pytest.approx(FLEXURES_PER_METRE * LENGTH_ALL[0] / 100.0)
    assert FLEXURES_PER_METRE == pytest.approx(5.75, abs=0.01)
    for count, cm in FLEXURES_HANSON.values():
        assert count / cm * 100.0 == pytest.approx(FLEXURES_PER_METRE, rel=0.02)
    within_published(counts, mean, sd, 505)
    slope = np.polyfit(lengths, counts, 1)[0]
    assert slope == pytest.approx(FLEXURES_PER_METRE, rel=0.2)
    assert FLEXURES_KHASHAB[1] / FLEXURES_KHASHAB[0] == pytest.approx(sd / mean)


@pytest.mark.slow
def test_the_population_tier_is_built_with_its_flexures():
    """Five patients of the population tier (seeds 1003, 1005-1008: the quickest of its
    first twenty to bend, 8-30 s each), built: each course's flexures by the rule are its
    drawn count in at least 4 of them and within one in all; the bent course keeps each
    segment's drawn length (to 1 mm) and passes the course's checks. (The first twenty:
    17 exact, 20 within one; docs/models/colon.md, "Acute-angle flexures".
    benchmarks/population_flexures.py measures more.)"""
    from capsule_drake.anatomy.course import (MIN_CLEARANCE, MIN_CURVATURE_RATIO,
                                              course_defects, nominal_radius)
    exact = 0
    for seed in (1003, 1005, 1006, 1007, 1008):
        request = dataclasses.replace(ColonParams(seed=seed), source=Population())
        params, (s, points, boundaries, targets) = resolve_population(request)
        patient = resolved_patient(request)
        found = len(acute_flexures(s, points))
        assert found == patient.flexures_built
        assert abs(found - patient.flexures) <= 1, (seed, found, patient.flexures)
        exact += found == patient.flexures
        np.testing.assert_allclose(np.diff(boundaries),
                                   [targets[name] for name in SEGMENT_NAMES], atol=1e-3)
        ratio, clearance = course_defects(s, points, nominal_radius(s, boundaries, params))
        assert ratio >= MIN_CURVATURE_RATIO and clearance >= MIN_CLEARANCE
    assert exact >= 4


@pytest.mark.slow
def test_the_procedural_courses_flexures_fall_short_of_the_published_count():
    """The procedural course (the standard tier's colons, kept as they were): seeds 0-9
    have 4-5 acute-angle flexures, the sigmoid loop's two bends and the two flexures, where
    the population's patients have their drawn count (above)."""
    counts = [len(acute_flexures(*solve_course(ColonParams(seed=seed),
                                               np.random.default_rng(seed))[:2]))
              for seed in range(10)]
    assert all(4 <= c <= 5 for c in counts), counts
