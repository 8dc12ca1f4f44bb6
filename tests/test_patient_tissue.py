"""The patient's colon wall (physics/contact/tissue.py): drawn per patient from the published
spreads, at a named corner or a percentile; the population's other streams untouched."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from capsule_drake.anatomy import ColonParams
from capsule_drake.anatomy.lesions import drawn_lesions
from capsule_drake.anatomy.params import Lesions, Population
from capsule_drake.anatomy.population import (resolve_population, sample_patient,
                                              shape_params)
from capsule_drake.app.benchmark import COLUMNS, tissue_columns
from capsule_drake.physics.contact import CompliantWall, RigidWall
from capsule_drake.physics.contact.compliant import check_compliant_wall, foundation_modulus
from capsule_drake.physics.contact.tissue import (CORNERS, GRIP, HIGH, LOW, MIDDLE, SPREADS,
                                                  STIFFNESS, TISSUE_CHOICES, TISSUE_COLUMNS,
                                                  patient_tissue, patient_wall,
                                                  tissue_metrics)
from capsule_drake.scenario import ScenarioError, load_scenario

N = 4000


def population(seed, **request):
    return dataclasses.replace(ColonParams(seed=seed), source=Population(**request))


@pytest.fixture(scope="module")
def drawn():
    """Each figure of the walls of N patients (seeds 0 to N - 1)."""
    walls = [patient_tissue(seed).values for seed in range(N)]
    return {name: np.array([wall[name] for wall in walls]) for name in SPREADS}


def test_a_patients_wall_is_drawn_once_per_seed():
    first = [patient_tissue(seed) for seed in range(50)]
    assert first == [patient_tissue(seed) for seed in range(50)]
    # Each figure differs between patients; the traits asked of the colon do not move it.
    for name in SPREADS:
        assert len({t.values[name] for t in first}) == 50
    wall = CompliantWall()
    assert patient_wall(wall, population(7)) == patient_wall(
        wall, population(7, sex="male", length_percentile=20, sigmoid="redundant"))
    assert patient_wall(wall, population(7)) != patient_wall(wall, population(8))


def test_drawn_walls_stay_in_their_bounds_and_have_the_stated_spreads(drawn):
    """4000 patients: every figure within its truncation; thickness 2.57 +- 1.05 mm and
    modulus 0.55 +- 0.73 MPa (the published 2.61 +- 1.29 and 0.63 +- 1.25 less the tails
    cut, module docstring); the medians those of the parents; the support log-uniform."""
    for name, spread in SPREADS.items():
        assert spread.low <= drawn[name].min() and drawn[name].max() <= spread.high, name
    assert SPREADS["thickness"].low == 1e-3 and SPREADS["thickness"].high == 6e-3
    se = 1.0 / math.sqrt(N)
    assert drawn["thickness"].mean() == pytest.approx(2.57e-3, abs=4 * 1.05e-3 * se)
    assert drawn["thickness"].std() == pytest.approx(1.05e-3, rel=0.05)
    assert np.median(drawn["thickness"]) == pytest.approx(2.36e-3, rel=0.03)
    assert np.median(drawn["circumferential_modulus"]) == pytest.approx(0.28e6, rel=0.08)
    assert drawn["circumferential_modulus"].mean() == pytest.approx(0.55e6, rel=0.06)
    assert SPREADS["circumferential_modulus"].low == pytest.approx(15.0e3, rel=0.01)
    assert SPREADS["circumferential_modulus"].high == pytest.approx(5.36e6, rel=0.01)
    assert np.median(drawn["friction"]) == pytest.approx(0.09, rel=0.05)
    assert (SPREADS["friction"].low, SPREADS["friction"].high) == pytest.approx((0.0212, 0.382),
                                                                              rel=0.01)
    logs = np.log10(drawn["support_stiffness"])
    assert (logs.min(), logs.max()) == pytest.approx((5.0, 7.0), abs=0.01)
    assert np.histogram(logs, bins=4, range=(5, 7))[0] == pytest.approx([N / 4] * 4,
                                                                       abs=4 * math.sqrt(N / 4))
    # The 5th, 50th and 95th percentiles as docs/sources.md section 3.6 gives them.
    stated = {"thickness": (1.22e-3, 2.36e-3, 4.68e-3),
              "circumferential_modulus": (39e3, 0.28e6, 2.04e6),
              "support_stiffness": (1.26e5, 1e6, 7.9e6), "friction": (0.034, 0.09, 0.24)}
    for name, values in stated.items():
        assert [SPREADS[name].quantile(p / 100) for p in (LOW, MIDDLE, HIGH)] == pytest.approx(
            values, rel=0.015), name
    # The nominal wall's place among the patients (module docstring).
    nominal = CompliantWall()
    assert [round(100 * SPREADS[n].cdf(getattr(nominal, n))) for n in SPREADS] == [
        59, 74, 24, 50]


@pytest.mark.parametrize("corner", sorted(CORNERS))
def test_a_corner_is_its_stated_percentile_of_each_figure(corner, drawn):
    """The corner's figures are the quantiles of the stated percentiles (LOW, MIDDLE, HIGH),
    the same for every seed; among 4000 drawn patients the share below each is that
    percentile (within 4 binomial standard errors)."""
    stiff, grip = CORNERS[corner]
    wall = patient_tissue(3, corner)
    assert wall == patient_tissue(12345, corner) and wall.how == corner
    for name, spread in SPREADS.items():
        p = stiff if name in STIFFNESS else grip
        assert p in (LOW, MIDDLE, HIGH)
        assert wall.values[name] == spread.quantile(p / 100.0)
        assert wall.percentiles[name] == p
        assert spread.cdf(wall.values[name]) == pytest.approx(p / 100.0, abs=1e-9)
        share = np.mean(drawn[name] < wall.values[name])
        q = p / 100.0
        assert abs(share - q) < 4 * math.sqrt(q * (1 - q) / N), (name, share)
    assert set(STIFFNESS) | set(GRIP) == set(SPREADS)


def test_the_corners_order_the_wall():
    """Soft corners have the softest foundation, stiff the stiffest; slippery the lowest
    friction, sticky the highest; a percentile puts every figure there."""
    radius = 0.02

    def k(tissue):
        return foundation_modulus(patient_wall(CompliantWall(), population(0, tissue=tissue)),
                                  radius)

    assert k("soft") == k("soft_slippery") == k("soft_sticky") < k("slippery") == k("sticky")
    assert k("sticky") < k("stiff") == k("stiff_slippery") == k("stiff_sticky")
    friction = {c: patient_tissue(0, c).values["friction"] for c in CORNERS}
    assert friction["slippery"] == friction["soft_slippery"] == friction["stiff_slippery"]
    assert friction["soft"] == friction["stiff"] == pytest.approx(0.09)
    assert friction["sticky"] == friction["soft_sticky"] == friction["stiff_sticky"]
    assert friction["slippery"] < friction["soft"] < friction["sticky"]
    low = patient_tissue(0, percentile=LOW)
    assert low.values == patient_tissue(0, "soft_slippery").values
    assert low.how == "percentile 5"
    assert patient_tissue(9, percentile=HIGH).values == patient_tissue(1, "stiff_sticky").values
    assert patient_tissue(9, percentile=MIDDLE).values["friction"] == pytest.approx(0.09)
    # Every corner's wall passes the compliant wall's own check.
    for corner in CORNERS:
        check_compliant_wall(patient_wall(CompliantWall(), population(0, tissue=corner)))


def test_patient_wall_replaces_the_tissue_figures_only_and_only_for_a_drawn_patient():
    wall = CompliantWall(through_thickness_modulus=2.0e6, hunt_crossley_dissipation=7.0,
                         drag_translational=2.0, lumen_radius=0.02)
    patient = patient_wall(wall, population(11))
    assert patient is not wall
    drawn = patient_tissue(11).values
    for item in dataclasses.fields(wall):
        expected = drawn[item.name] if item.name in SPREADS else getattr(wall, item.name)
        assert getattr(patient, item.name) == expected, item.name
    assert patient_wall(patient, population(11)) == patient   # once or twice: the same
    # The nominal wall unchanged: a procedural colon, tissue: nominal, the rigid stand-in.
    assert patient_wall(wall, ColonParams(seed=11)) is wall
    assert patient_wall(wall, population(11, tissue="nominal")) is wall
    rigid = RigidWall()
    assert patient_wall(rigid, population(11)) is rigid
    assert patient_wall(rigid, population(11, tissue="stiff")) is rigid


def test_metrics_and_benchmark_columns_say_what_the_wall_was():
    drawn = tissue_metrics(CompliantWall(), population(5))
    values = patient_tissue(5).values
    assert drawn["tissue"] == "drawn"
    assert drawn["tissue_thickness_mm"] == pytest.approx(1e3 * values["thickness"], abs=1e-4)
    assert drawn["tissue_modulus_MPa"] == pytest.approx(
        1e-6 * values["circumferential_modulus"], abs=1e-5)
    assert drawn["tissue_support_MPa_per_m"] == pytest.approx(
        1e-6 * values["support_stiffness"], abs=1e-5)
    assert drawn["tissue_friction"] == pytest.approx(values["friction"], abs=1e-5)
    assert set(drawn["tissue_percentiles"]) == set(SPREADS)
    corner = tissue_metrics(CompliantWall(), population(5, tissue="stiff_slippery"))
    assert corner["tissue"] == "stiff_slippery"
    assert corner["tissue_percentiles"] == {"thickness": HIGH, "circumferential_modulus": HIGH,
                                            "support_stiffness": HIGH, "friction": LOW}
    assert tissue_metrics(CompliantWall(), population(5, tissue_percentile=30))["tissue"] \
        == "percentile 30"
    nominal = tissue_metrics(CompliantWall(thickness=3e-3), ColonParams(seed=5))
    assert nominal == {"tissue": "nominal", "tissue_thickness_mm": 3.0,
                       "tissue_modulus_MPa": 0.63, "tissue_support_MPa_per_m": 0.3,
                       "tissue_friction": 0.09, "tissue_percentiles": None}
    rigid = tissue_metrics(RigidWall(), population(5))
    assert rigid["tissue"] == "none (rigid stand-in)" and rigid["tissue_thickness_mm"] is None
    # The benchmark's row: the same figures, NaN where there are none.
    assert list(TISSUE_COLUMNS) == [c for c in COLUMNS if c.startswith("tissue")]
    assert COLUMNS.index("tissue") == COLUMNS.index("patient") + 1
    assert tissue_columns(drawn) == {key: drawn[key] for key in TISSUE_COLUMNS}
    row = tissue_columns(rigid)
    assert row["tissue"] == rigid["tissue"] and np.isnan(row["tissue_friction"])


# A population patient as it was drawn before the tissue was part of the patient: its
# length, segments and course (to the last digit on the machine that recorded them), and
# its lesions. The tissue's stream is of its own, so none of these may move.
BEFORE = {
    0: (1.6898481695830128, "female", 7),
    1000: (1.7538210738200901, "female", 11),
    1017: (1.338797488587803, "female", 8),
}
BEFORE_SEGMENTS_1000 = [0.1267526990477755, 0.6935468265171397, 0.3119284673954803,
                        0.3975701030585863, 0.15517860384080048, 0.06884437396030789]
BEFORE_COURSE_1000 = (1.7538237518272541, 281.13564398704534,
                      [0.12043535683500473, -0.09400956527529103, 0.07106725603474895])
BEFORE_LESION_1000 = (("0-IIa", "sigmoid"),   # kind, segment; size (mm), along, around (deg)
                      (4.1521501693025336, 0.011441775949128541, 341.7977376121882))


@pytest.mark.slow
def test_the_populations_other_streams_are_unchanged():
    for seed, (total, sex, flexures) in BEFORE.items():
        for request in ({}, {"tissue": "soft_sticky"}, {"tissue_percentile": 80.0}):
            patient = sample_patient(Population(**request), seed)
            assert patient.total_length == pytest.approx(total, rel=1e-12)
            assert (patient.sex, patient.flexures) == (sex, flexures)
    assert list(sample_patient(Population(), 1000).lengths.values()) == pytest.approx(
        BEFORE_SEGMENTS_1000, rel=1e-12)
    params = dataclasses.replace(population(1000), lesions=Lesions())
    resolved, (s, points, boundaries, _) = resolve_population(params, bend=False)
    assert float(s[-1]) == pytest.approx(BEFORE_COURSE_1000[0], rel=1e-9)
    assert float(points.sum()) == pytest.approx(BEFORE_COURSE_1000[1], rel=1e-9)
    assert points[800].tolist() == pytest.approx(BEFORE_COURSE_1000[2], rel=1e-9)
    lesion = drawn_lesions(resolved)[0]
    assert (lesion.kind, lesion.segment) == BEFORE_LESION_1000[0]
    assert (lesion.size_mm, lesion.along, lesion.around_deg) == pytest.approx(
        BEFORE_LESION_1000[1], rel=1e-12)
    # Another wall asked for: the same colon (resolved once, its files cached under one
    # key), the request its own.
    stiff = dataclasses.replace(params, source=Population(tissue="stiff"))
    other, (s2, points2, _, _) = resolve_population(stiff, bend=False)
    assert np.array_equal(points2, points) and np.array_equal(s2, s)
    assert other.population.tissue == "stiff" and resolved.population.tissue == "drawn"
    assert dataclasses.replace(other, source=resolved.source) == resolved
    assert shape_params(stiff) == shape_params(params) == params
    assert shape_params(ColonParams(seed=3)) == ColonParams(seed=3)


@pytest.mark.parametrize("text, key, names", [
    ("{colon: {source: !Population {tissue: squishy}}}", "colon.source.tissue", True),
    ("{colon: {source: !Population {tissue: soft-sticky}}}", "colon.source.tissue", True),
    ("{colon: {source: !Population {tissue_percentile: 0}}}", "colon.source.tissue_percentile",
     False),
    ("{colon: {source: !Population {tissue_percentile: 100}}}",
     "colon.source.tissue_percentile", False),
    ("{colon: {source: !Population {tissue_percentile: -5}}}",
     "colon.source.tissue_percentile", False),
    ("{colon: {source: !Population {tissue_percentile: .nan}}}",
     "colon.source.tissue_percentile", False),
    ("{colon: {source: !Population {tissue: stiff, tissue_percentile: 20}}}",
     "colon.source.tissue_percentile", False),
])
def test_a_bad_tissue_request_is_one_line_at_load(text, key, names):
    with pytest.raises(ScenarioError) as error:
        load_scenario(override=text)
    message = str(error.value)
    assert key in message and "\n" not in message, message
    if names:   # the known choices listed
        assert all(choice in message for choice in TISSUE_CHOICES), message


def test_every_tissue_choice_loads_and_is_documented():
    params = (Path(__file__).resolve().parents[1] / "capsule_drake" / "anatomy"
              / "params.py").read_text()
    for choice in TISSUE_CHOICES:
        scenario = load_scenario(override=f"{{colon: {{source: !Population {{tissue: {choice}}}}}}}")
        assert scenario.colon.population.tissue == choice
        assert f'"{choice}"' in params, choice
    assert load_scenario(override="{colon: {source: !Population {tissue_percentile: 12.5}}}"
                         ).colon.population.tissue_percentile == 12.5


@pytest.mark.slow
def test_the_station_builds_the_patients_wall():
    # The contact the plant is given is the patient's: a stiff patient's capsule layer (its
    # modulus k r) is stiffer than a soft one's, and the friction is the drawn one.
    from capsule_drake.scenario import load_scenario
    from capsule_drake.station import make_station
    from capsule_drake.physics.contact.tissue import patient_wall
    moduli = {}
    for corner in ("soft", "stiff"):
        scenario = load_scenario(name="Default", override=(
            "{contact: !CompliantWall {}, colon: {source: !Population {tissue: %s}}}" % corner))
        station = make_station(scenario)
        plant = station.GetSubsystemByName("plant")
        inspector = station.GetSubsystemByName("scene_graph").model_inspector()
        body = plant.GetBodyByName("capsule")
        props = [inspector.GetProximityProperties(g)
                 for g in plant.GetCollisionGeometriesForBody(body)]
        props = [p for p in props if p is not None]
        moduli[corner] = props[0].GetProperty("hydroelastic", "hydroelastic_modulus")
        friction = props[0].GetProperty("material", "coulomb_friction").static_friction()
        wall = patient_wall(scenario.contact, scenario.colon)
        assert friction == pytest.approx(wall.friction)
    assert moduli["stiff"] > 3.0 * moduli["soft"]
