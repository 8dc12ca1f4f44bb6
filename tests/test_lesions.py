"""Lesions drawn for patients (anatomy/lesions.py) against the published figures they come
from (docs/sources.md section 3.4), and against figures from other studies that were not
used to draw them."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from capsule_drake.anatomy import lesions as L
from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.lesion_geometry import floor_angle
from capsule_drake.anatomy.params import SEGMENT_NAMES, ColonParams, Lesions, PlacedLesion
from capsule_drake.scenario import ScenarioError, load_scenario
from capsule_drake.station import make_station

PATIENTS = 1000
# The published figures, written out here (not read from the module under test).
SIZE_SHARES = {"diminutive": 0.736, "small": 0.227, "large": 0.037}        # 269 polyps
POLYP_SEGMENTS = {"rectum": 0.257, "sigmoid": 0.294, "descending": 0.097,
                  "transverse": 0.167, "ascending": 0.175, "cecum": 0.011}  # the same
DIVERTICULUM_SEGMENTS = {"sigmoid": 0.75, "descending": 0.11, "transverse": 0.06,
                         "ascending": 0.08, "rectum": 0.0, "cecum": 0.0}    # 260 patients
Z = 2.58   # two-sided 99 %: 16 comparisons below, each with a ~1 % chance of a false alarm


def within(sampled: float, n_sampled: int, published: float, n_published: int) -> bool:
    """A sampled share and a published one agree within their combined binomial
    uncertainty (Z standard errors)."""
    se = np.sqrt(published * (1 - published) / n_published
                 + published * (1 - published) / n_sampled)
    return abs(sampled - published) <= Z * se


@pytest.fixture(scope="module")
def population():
    return [L.drawn_lesions(ColonParams(seed=seed, lesions=Lesions()))
            for seed in range(PATIENTS)]


def test_polyp_prevalence_per_patient(population):
    # Lieberman et al. 2008: 6360 of 13,992 screening patients had a polyp.
    share = np.mean([any(x.polyp for x in patient) for patient in population])
    assert within(share, PATIENTS, 6360 / 13992, 13992), share


def test_polyps_per_size_class_and_segment(population):
    polyps = [x for patient in population for x in patient if x.polyp]
    n = len(polyps)
    assert 700 < n < 1400      # 45 % of 1000 patients with 2.3 each: ~1035
    # The trial arm the shares come from: 269 polyps.
    for name, published in SIZE_SHARES.items():
        share = np.mean([x.size_class == name for x in polyps])
        assert within(share, n, published, 269), (name, share)
    for name in SEGMENT_NAMES:
        share = np.mean([x.segment == name for x in polyps])
        assert within(share, n, POLYP_SEGMENTS[name] / 1.001, 269), (name, share)
    assert all(2.0 <= round(x.size_mm) <= 30.0 for x in polyps)


def test_polyps_against_studies_not_used_to_draw_them(population):
    polyps = [x for patient in population for x in patient if x.polyp]
    n = len(polyps)
    # Rex et al. 2020: 2236 of 2986 resected polyps were 1-5 mm.
    diminutive = np.mean([x.size_class == "diminutive" for x in polyps])
    assert within(diminutive, n, 2236 / 2986, 2986), diminutive
    # Conventional adenomas: "5-10 % pedunculated" (a review's table, S).
    pedunculated = np.mean([x.kind == "0-Ip" for x in polyps])
    assert 0.05 - Z * np.sqrt(0.05 * 0.95 / n) <= pedunculated <= 0.10 + Z * np.sqrt(
        0.1 * 0.9 / n), pedunculated
    # The SUN database: pedunculated polyps concentrate among the large ones (12 of 20 at
    # >= 10 mm against 2 of 60 at <= 5 mm), and so they must here.
    large = [x.kind == "0-Ip" for x in polyps if x.size_class == "large"]
    small = [x.kind == "0-Ip" for x in polyps if x.size_class == "diminutive"]
    assert np.mean(large) > 5 * np.mean(small)


def test_diverticula_prevalence_count_and_segments(population):
    # Peery et al. 2016: 260 of 624 screening patients; 14 per affected patient on average
    # (1-158); 75 / 11 / 6 / 8 % in the sigmoid, descending, transverse and ascending colon.
    affected = [[x for x in patient if not x.polyp] for patient in population]
    affected = [d for d in affected if d]
    assert within(len(affected) / PATIENTS, PATIENTS, 260 / 624, 624)
    counts = np.array([len(d) for d in affected])
    assert abs(counts.mean() - 14.0) < 2.0, counts.mean()     # no SD is published (U)
    assert counts.min() >= 1 and counts.max() <= L.DIVERTICULA_MAX
    every = [x for d in affected for x in d]
    for name, published in DIVERTICULUM_SEGMENTS.items():
        share = np.mean([x.segment == name for x in every])
        if published == 0.0:
            assert share == 0.0, name
        else:   # the patients (260), not their diverticula, are the independent draws
            assert within(share, len(affected), published, 260), (name, share)
    assert all(5.0 <= x.size_mm <= 10.0 for x in every)


def test_a_patient_keeps_their_lesions():
    params = ColonParams(seed=12, lesions=Lesions())
    first = L.drawn_lesions(params)
    assert first == L.drawn_lesions(ColonParams(seed=12, lesions=Lesions()))
    no_diverticula = L.drawn_lesions(ColonParams(seed=12, lesions=Lesions(diverticula=False)))
    assert no_diverticula == [x for x in first if x.polyp]
    other = L.drawn_lesions(ColonParams(seed=99, lesions=Lesions(seed=12)))
    assert other == first
    assert L.drawn_lesions(ColonParams(seed=12)) == []
    placed = PlacedLesion(kind="0-Ip", size_mm=12.0, segment="transverse", along=0.3)
    only = L.drawn_lesions(ColonParams(seed=12, lesions=Lesions(drawn=False,
                                                                 placed=[placed])))
    assert only == [L.DrawnLesion("0-Ip", 12.0, "transverse", 0.3, 90.0)]
    assert only[0].size_class == "large"


@pytest.mark.parametrize("text, key", [
    ("{colon: {lesions: {placed: [{kind: 0-III}]}}}", "colon.lesions.placed[0].kind"),
    ("{colon: {lesions: {placed: [{size_mm: 0}]}}}", "colon.lesions.placed[0].size_mm"),
    ("{colon: {lesions: {placed: [{segment: ileum}]}}}", "colon.lesions.placed[0].segment"),
    ("{colon: {lesions: {placed: [{along: 2}]}}}", "colon.lesions.placed[0].along"),
    ("{colon: {lesions: {seed: -1}}}", "colon.lesions.seed"),
    ("{colon: {lesions: {polyp: true}}}", "colon.lesions.polyp"),
    ("{colon: {lesions: {placed: [{kind: diverticulum, size_mm: 30}]}}}",
     "colon.lesions.placed[0].size_mm"),
    ("{colon: {source: !ExVivo {}, lesions: {placed: [{kind: diverticulum}]}}}",
     "colon.lesions.placed[0].kind"),
])
def test_a_wrong_lesion_is_one_line_at_load(text, key):
    with pytest.raises(ScenarioError) as error:
        load_scenario(override=text)
    message = str(error.value)
    assert key in message and "\n" not in message


@pytest.mark.slow
def test_the_capsule_rests_on_a_polyp_under_it():
    """Felt by the capsule: a sessile polyp placed where the default capsule rests against
    the wall (after 1 s) lifts it off the wall toward the centreline, a larger one more."""
    def rest(text: str):
        station = make_station(load_scenario(name="Default", override=text))
        simulator = Simulator(station)
        simulator.AdvanceTo(1.0)
        return station.GetOutputPort("capsule.state").Eval(simulator.get_context())[4:7]

    colon, _ = load_colon(load_scenario(name="Default").colon)
    s, radial, theta = colon.centerline.closest(rest("{}"))
    start, end = colon.centerline.segment_ranges()["rectum"]
    margin = min(0.01, 0.25 * (end - start))
    along = (s - start - margin) / (end - start - 2 * margin)
    around = np.degrees(theta - floor_angle(colon, s))
    lifted = []
    for size in (6.0, 14.0):
        text = (f"{{colon: {{lesions: {{drawn: false, placed: [{{kind: 0-Is, size_mm: {size},"
                f" segment: rectum, along: {along:.5f}, around_deg: {around:.3f}}}]}}}}}}")
        lifted.append(radial - colon.centerline.closest(rest(text))[1])
    assert lifted[1] > 1e-3 and lifted[1] > lifted[0] > 0.0, lifted
