"""The compliant wall's foundation realisation (physics/contact/foundation.py), each figure
against a second route: the displaced volume's closed form, a capsule's weight at rest,
Coulomb's law on an incline, and the colon's own wall radius."""

import math

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import ExternallyAppliedSpatialForce, MultibodyPlant
from pydrake.multibody.tree import BodyIndex, SpatialInertia, UnitInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource

from capsule_drake.capsule.model import capsule_model
from capsule_drake.physics.contact.compliant import (CompliantWall, bilinear_volume_force,
                                                     displaced_volume_force, foundation_modulus,
                                                     knee_depth)
from capsule_drake.physics.contact.foundation import (FoundationContact, StraightTube,
                                                     WallTable, no_forces)

MASS, TRANSVERSE, AXIAL = 0.012, 1.093e-6, 2.02e-7   # models/capsule.sdf
K = 3.0e6                                             # Pa/m, the nominal wall's order


def FlatTube(radius=2.0, length=0.3):
    """A straight tube along x of radius 2 m: flat across the capsule's patch, within
    0.01 mm; the capsule lies on its floor (theta = pi)."""
    return StraightTube(radius, length)


def capsule_state(depth, roll=0.0, radius=2.0):
    """The capsule lying along the tube on its floor, `depth` (m) into it, at rest."""
    model = capsule_model()
    q = (RotationMatrix.MakeYRotation(math.pi / 2)
         @ RotationMatrix.MakeZRotation(roll)).ToQuaternion()
    p = [0.15, 0.0, -(radius - model.radius + depth)]
    return np.r_[q.w(), q.x(), q.y(), q.z(), p, np.zeros(6)]


def wall_system(tube, friction=0.09, dissipation=0.0, time_step=2e-3, **stiffening):
    model = capsule_model()
    return FoundationContact(BodyIndex(1), WallTable(tube), RigidTransform(), model.radius,
                             model.length, K, friction, dissipation, time_step, MASS, AXIAL,
                             **stiffening)


@pytest.mark.parametrize("roll", [0.0, math.pi / 40, math.pi / 20])  # on a cell, between
def test_the_wall_pushes_back_with_its_closed_form(roll):
    # k times the capsule's volume beyond the mucosa: within 5 % over the indentations runs
    # reach, from a capsule lying under its weight (~0.7 mm) to one half buried.
    model = capsule_model()
    system = wall_system(FlatTube())
    context = system.CreateDefaultContext()
    system.GetInputPort("other_forces").FixValue(context, [])
    for depth in (0.0002, 0.0003, 0.0005, 0.001, 0.002, 0.004, model.radius):
        system.GetInputPort("capsule_state").FixValue(context, capsule_state(depth, roll))
        wrench = system.wall_wrench(context)
        closed = displaced_volume_force(K, depth, model.radius, model.length)
        assert wrench[5] == pytest.approx(closed, rel=0.05), (depth, wrench[5], closed)
        # Straight up, through the capsule's axis: no side force, no torque.
        assert np.allclose(wrench[3:5], 0.0, atol=1e-9 + 1e-6 * closed)
        assert np.allclose(wrench[:3], 0.0, atol=1e-9 + 1e-6 * closed)


@pytest.mark.parametrize("knee", [0.0005, 0.002])
def test_past_its_knee_the_wall_pushes_back_with_the_bilinear_closed_form(knee):
    # The stiffened wall (compliant.py knee_strain, stiffening): k d up to the knee, then
    # 7.71 k more per metre; the closed form k V(d) + (k2 - k) V(d - knee) within 5 %, and
    # below the knee the linear wall's force exactly.
    model = capsule_model()
    k_stiff = 7.71 * K
    system = wall_system(FlatTube(), knee_depth=knee, stiffened_modulus=k_stiff)
    linear = wall_system(FlatTube())
    context, plain = system.CreateDefaultContext(), linear.CreateDefaultContext()
    for s, c in ((system, context), (linear, plain)):
        s.GetInputPort("other_forces").FixValue(c, [])
    for depth in (0.0003, 0.001, 0.002, 0.003, 0.004, model.radius, 1.5 * model.radius):
        state = capsule_state(depth)
        system.GetInputPort("capsule_state").FixValue(context, state)
        linear.GetInputPort("capsule_state").FixValue(plain, state)
        force = system.wall_wrench(context)[5]
        closed = bilinear_volume_force(K, k_stiff, knee, depth, model.radius, model.length)
        assert force == pytest.approx(closed, rel=0.05), (depth, force, closed)
        if depth <= knee:
            assert force == pytest.approx(linear.wall_wrench(plain)[5], rel=1e-12)
        else:
            assert force > 1.2 * linear.wall_wrench(plain)[5]


def test_the_stiffened_modulus_and_knee_follow_from_the_wall():
    wall = CompliantWall()
    R = 0.02
    hoop = wall.circumferential_modulus * wall.thickness / R**2
    through = wall.through_thickness_modulus / wall.thickness
    for stiffened, factor in ((False, 1.0), (True, wall.stiffening)):
        outward = factor * hoop + wall.support_stiffness
        assert foundation_modulus(wall, R, stiffened) == pytest.approx(
            outward * through / (outward + through))
    assert knee_depth(wall, R) == pytest.approx(wall.knee_strain * R)
    assert knee_depth(CompliantWall(stiffening=1.0), R) == math.inf
    # The bilinear closed form is the linear one below the knee, and beyond it the linear
    # one plus the extra stiffness times the volume past the knee's surface.
    r, L = capsule_model().radius, capsule_model().length
    assert bilinear_volume_force(K, 5 * K, 0.002, 0.0015, r, L) == pytest.approx(
        displaced_volume_force(K, 0.0015, r, L))
    assert bilinear_volume_force(K, 5 * K, 0.002, 0.003, r, L) == pytest.approx(
        displaced_volume_force(K, 0.003, r, L) + displaced_volume_force(4 * K, 0.001, r, L))


def test_the_closed_form_is_the_displaced_volume():
    # A second route: the volume of a capsule below a plane, by summing thin slices.
    model = capsule_model()
    r, L = model.radius, model.length
    for depth in (0.0003, 0.002, r):
        z = np.linspace(-0.5 * L - r, 0.5 * L + r, 40001)
        rho = np.sqrt(np.maximum(r**2 - np.maximum(np.abs(z) - 0.5 * L, 0.0) ** 2, 0.0))
        c = np.clip((r - depth) / np.maximum(rho, 1e-12), -1.0, 1.0)
        segment = rho**2 * (np.arccos(c) - c * np.sqrt(1 - c**2))
        volume = np.trapezoid(segment, z)
        assert displaced_volume_force(K, depth, r, L) == pytest.approx(K * volume, rel=2e-3)


@pytest.mark.parametrize("energy", [0.55, 1.98])   # J/m^2: Terry 2012's peel and tack
def test_pulling_a_stuck_capsule_off_costs_the_adhesion_energy_over_its_contact(energy):
    # A second route for the adhesion: the work of lifting a capsule pressed d0 into a flat
    # wall until it lets go is the elastic energy the wall gives back (the closed form's
    # force integrated over the depth) less the adhesion energy times the area it touched
    # (2 a L + pi a^2, a the contact's half-width).
    model = capsule_model()
    r, L = model.radius, model.length
    system = FoundationContact(BodyIndex(1), WallTable(FlatTube()), RigidTransform(), r, L, K,
                               0.09, 0.0, 2e-3, MASS, AXIAL, adhesion_energy=energy)
    context = system.CreateDefaultContext()
    system.GetInputPort("other_forces").FixValue(context, [])
    d0 = 0.002
    system.GetInputPort("capsule_state").FixValue(context, capsule_state(d0))
    context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))  # stuck
    release = math.sqrt(2.0 * energy / K)
    lifts = np.linspace(0.0, d0 + release + 2e-4, 3001)
    forces = []
    for u in lifts:
        system.GetInputPort("capsule_state").FixValue(context, capsule_state(d0 - u))
        forces.append(system.wall_wrench(context)[5])
    forces = np.array(forces)
    assert forces[-1] == 0.0                      # let go
    assert forces.min() < -0.5 * K * release * L * 1e-3  # pulled back while stuck
    work = np.trapezoid(forces, lifts)
    depths = np.linspace(0.0, d0, 2001)
    elastic = np.trapezoid(displaced_volume_force(K, depths, r, L), depths)
    a = math.sqrt(r**2 - (r - d0) ** 2)
    # The adhesion's share (measured: 5 % under the closed form, the cells' quantisation
    # of the contact's edge): within 10 %.
    adhesion = energy * (2.0 * a * L + math.pi * a**2)
    assert elastic - work == pytest.approx(adhesion, rel=0.1), (work, elastic, adhesion)


def test_without_adhesion_a_capsule_lets_go_at_the_mucosa():
    model = capsule_model()
    system = wall_system(FlatTube())
    context = system.CreateDefaultContext()
    system.GetInputPort("other_forces").FixValue(context, [])
    system.GetInputPort("capsule_state").FixValue(context, capsule_state(0.002))
    context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
    system.GetInputPort("capsule_state").FixValue(context, capsule_state(-1e-5))
    assert system.wall_wrench(context)[5] == 0.0
    assert model.radius > 0


def falling_capsule(gravity, friction=0.09, time_step=2e-3, dissipation=5.0):
    """A diagram of the capsule as a free body on the flat tube's floor with the wall's
    force, gravity `gravity` (3,)."""
    builder = DiagramBuilder()
    plant = builder.AddSystem(MultibodyPlant(time_step))
    body = plant.AddRigidBody("capsule", SpatialInertia(
        MASS, np.zeros(3), UnitInertia(TRANSVERSE / MASS, TRANSVERSE / MASS, AXIAL / MASS)))
    plant.mutable_gravity_field().set_gravity_vector(gravity)
    plant.Finalize()
    model = capsule_model()
    wall = builder.AddSystem(FoundationContact(
        body.index(), WallTable(FlatTube()), RigidTransform(), model.radius, model.length, K,
        friction, dissipation, time_step, MASS, AXIAL,
        np.diag([TRANSVERSE, TRANSVERSE, AXIAL, MASS, MASS, MASS]), gravity_W=gravity))
    none = builder.AddSystem(ConstantValueSource(no_forces()))
    builder.Connect(none.get_output_port(), wall.GetInputPort("other_forces"))
    builder.Connect(plant.get_state_output_port(), wall.GetInputPort("capsule_state"))
    builder.Connect(wall.GetOutputPort("applied_spatial_force"),
                    plant.get_applied_spatial_force_input_port())
    diagram = builder.Build()
    return diagram, plant, body, wall


def test_a_capsule_comes_to_rest_as_deep_as_its_weight_needs():
    # At rest, k V(depth) = m g: the depth from the closed form, the simulated one from the
    # plant (a 2 ms step: the wall's force is linearly implicit, so its step does not bias
    # where the capsule rests).
    model = capsule_model()
    g = 9.81
    diagram, plant, body, wall = falling_capsule(np.array([0.0, 0.0, -g]))
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    x0 = capsule_state(0.0)
    plant.SetPositionsAndVelocities(plant.GetMyMutableContextFromRoot(context), x0)
    simulator.AdvanceTo(1.0)
    x = plant.GetPositionsAndVelocities(plant.GetMyContextFromRoot(context))
    depth = -x[6] - (2.0 - model.radius)
    depths = np.linspace(1e-5, 3e-3, 30001)
    expected = depths[np.searchsorted(
        displaced_volume_force(K, depths, model.radius, model.length), MASS * g)]
    assert depth == pytest.approx(expected, rel=0.03)
    assert np.linalg.norm(x[7:]) < 1e-3   # at rest


@pytest.mark.parametrize("slope, slides", [(0.06, False), (0.15, True)])
def test_on_an_incline_the_capsule_sticks_below_mu_and_slides_above(slope, slides):
    # Coulomb's law along the capsule's axis (no rolling): held below tan(a) = mu = 0.09,
    # sliding above it at g (sin a - mu cos a).
    mu, g = 0.09, 9.81
    gravity = g * np.array([-math.sin(slope), 0.0, -math.cos(slope)])
    diagram, plant, body, wall = falling_capsule(gravity, friction=mu)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    plant_context = plant.GetMyMutableContextFromRoot(context)
    depths = np.linspace(1e-5, 3e-3, 30001)
    model = capsule_model()
    rest = depths[np.searchsorted(displaced_volume_force(K, depths, model.radius, model.length),
                                  MASS * g * math.cos(slope))]
    plant.SetPositionsAndVelocities(plant_context, capsule_state(rest))
    # Half a second: a sliding capsule travels 7 cm of the 15 cm to the tube's end.
    simulator.AdvanceTo(0.25)
    x_quarter = plant.GetPositionsAndVelocities(plant_context)[4]
    simulator.AdvanceTo(0.5)
    x_half, v_half = plant.GetPositionsAndVelocities(plant_context)[[4, 10]]
    if slides:
        accel = g * (math.sin(slope) - mu * math.cos(slope))
        assert -v_half == pytest.approx(accel * 0.5, rel=0.05)
    else:
        assert abs(x_half - x_quarter) < 1e-5     # held: under 10 micrometres in 0.25 s
        assert abs(v_half) < 1e-4


def test_the_wall_table_reads_the_colon_wall_within_a_tenth_of_a_millimetre():
    # The depth of points near the wall, from the table, against the colon's own wall radius
    # at each point's closest centreline station (anatomy's route), on the Default colon.
    from capsule_drake.anatomy import load_colon
    from capsule_drake.scenario import load_scenario
    colon = load_colon(load_scenario(name="Default").colon)[0]
    table = WallTable(colon)
    centerline = colon.centerline
    rng = np.random.default_rng(7)
    errors = []
    for _ in range(120):
        s0 = rng.uniform(0.05, centerline.length - 0.05)
        _, n, b = centerline.frame_at(s0)
        angle = rng.uniform(0.0, 2.0 * math.pi)
        centre = centerline.point_at(s0) + (colon.wall_radius(s0, angle) - 0.006) * (
            math.cos(angle) * n + math.sin(angle) * b)
        direction = rng.normal(size=3)
        points = centre + np.linspace(-0.0157, 0.0157, 7)[:, None] * direction / np.linalg.norm(
            direction) + rng.normal(scale=0.003, size=(7, 3))
        depth, _ = table.depth(points, table.nearest(centre))
        s, rho, theta = centerline.closest(points)
        ds, dt = 1e-4, 1e-3
        radius = colon.wall_radius(s, theta)
        slope_s = (colon.wall_radius(s + ds, theta) - colon.wall_radius(s - ds, theta)) / (2 * ds)
        slope_t = (colon.wall_radius(s, theta + dt) - colon.wall_radius(s, theta - dt)) / (
            2 * dt * radius)
        exact = (rho - radius) / np.sqrt(1.0 + slope_s**2 + slope_t**2)
        near = np.abs(exact) < 0.006
        errors += list(np.abs(depth - exact)[near])
    errors = np.array(errors)
    assert np.percentile(errors, 99) < 1e-4
    assert np.median(errors) < 2e-5


@pytest.mark.slow
def test_both_realisations_drag_the_capsule_alike():
    # The same wall, two routes: the foundation computed here and Drake's hydroelastic
    # contact of the capsule's field mesh (pressure along the capsule's normal: 10 % less at
    # 2 mm). Over the Default drag's first 6 s they take the capsule to the same place.
    from pydrake.systems.analysis import Simulator as Sim
    from capsule_drake.anatomy import load_colon
    from capsule_drake.scenario import load_scenario
    from capsule_drake.station import make_station
    ends = []
    for realisation in ("foundation", "hydroelastic"):
        scenario = load_scenario(name="Default", override=(
            f"{{contact: !CompliantWall {{realisation: {realisation}}}}}"))
        station = make_station(scenario)
        simulator = Sim(station)
        simulator.Initialize()
        simulator.AdvanceTo(6.0)
        x = station.GetOutputPort("capsule.state").Eval(simulator.get_context())
        ends.append(np.array(x[4:7]))
        assert station.HasOutputPort("contact.wall") == (realisation == "foundation")
    colon = load_colon(scenario.colon)[0]
    s = [colon.centerline.closest(p)[0] for p in ends]
    assert abs(s[0] - s[1]) < 0.01, s


def test_the_near_wall_filter_keeps_every_point_beyond_the_wall():
    # The cheap filter before the table's lookup (WallTable.near_wall) must not drop a point
    # that is beyond the mucosa or a tube's end cap: capsules' cells placed at random along
    # the Default colon, at its bends and both ends, deep into the wall and across the lumen.
    from capsule_drake.anatomy import load_colon
    from capsule_drake.scenario import load_scenario
    from capsule_drake.physics.contact.foundation import capsule_probes
    model = capsule_model()
    colon = load_colon(load_scenario(name="Default").colon)[0]
    table = WallTable(colon)
    centerline = colon.centerline
    cells, _, _ = capsule_probes(model.radius, model.length)
    reach = float(np.linalg.norm(cells, axis=1).max())
    rng = np.random.default_rng(11)
    kept = beyond = 0
    for k in range(300):
        s0 = (rng.uniform(0.0, 0.03) if k % 3 == 0 else
              centerline.length - rng.uniform(0.0, 0.03) if k % 3 == 1 else
              rng.uniform(0.0, centerline.length))
        _, n, b = centerline.frame_at(s0)
        angle = rng.uniform(0.0, 2.0 * math.pi)
        offset = rng.uniform(0.0, colon.wall_radius(s0, angle) + 0.004)
        centre = (centerline.point_at(s0) + offset * (math.cos(angle) * n + math.sin(angle) * b)
                  + rng.normal(scale=0.004, size=3))
        R = RotationMatrix(np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1]).matrix()
        if np.linalg.det(R) < 0:
            R = -R
        points = cells @ R.T + centre
        station = table.follow(centre, table.nearest(centre))
        depth, _ = table.depth(points, station)
        inside = set(np.flatnonzero(depth > 0.0))
        near = set(table.near_wall(points, station, reach))
        assert inside <= near, (s0, sorted(inside - near)[:5])
        kept += len(near)
        beyond += len(inside)
    assert beyond > 1000          # the sample did press many cells into the wall


def _near_wall_numpy(table, points, station, reach, slack):
    # WallTable.near_wall's rule written with NumPy arrays (its compiled form's second route).
    from capsule_drake.physics.contact.foundation import CAP_REACH
    lowest, bend = table._filter(reach)
    frame = table.frames[station]
    local = (points - frame[0]) @ frame[1:].T
    sector = (np.arctan2(local[:, 2], local[:, 1]) / table.dtheta).astype(np.intp) % table.around
    along = np.abs(local[:, 0]) + slack
    near = (np.hypot(local[:, 1], local[:, 2]) + slack + bend[station] * along**2
            > lowest[station][sector])
    for end, sign in ((0, -1.0), (table.count - 1, 1.0)):
        if abs(station - end) * table.step <= CAP_REACH:
            near |= sign * ((points - table.frames[end, 0]) @ table.frames[end, 1]) > -1e-3 - slack
    return np.flatnonzero(near)


def test_the_compiled_near_wall_filter_and_placement_match_numpy():
    from capsule_drake.anatomy import load_colon
    from capsule_drake.physics.contact import foundation_kernels as kernels
    from capsule_drake.physics.contact.foundation import capsule_probes
    from capsule_drake.scenario import load_scenario
    model = capsule_model()
    colon = load_colon(load_scenario(name="Default").colon)[0]
    table = WallTable(colon)
    cells, _, _ = capsule_probes(model.radius, model.length)
    reach = float(np.linalg.norm(cells, axis=1).max())
    rng = np.random.default_rng(5)
    picked = 0
    for k in range(200):
        s0 = (rng.uniform(0.0, 0.05) if k % 4 == 0 else
              colon.centerline.length - rng.uniform(0.0, 0.05) if k % 4 == 1 else
              rng.uniform(0.0, colon.centerline.length))
        centre = colon.centerline.point_at(s0) + rng.normal(scale=0.01, size=3)
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        R *= np.sign(np.linalg.det(R))
        offsets, points = kernels.place_cells(cells, R, centre)
        np.testing.assert_allclose(offsets, cells @ R.T, atol=1e-15)
        np.testing.assert_allclose(points, cells @ R.T + centre, atol=1e-15)
        station = table.follow(centre, table.nearest(centre))
        slack = rng.choice([0.0, 3e-4, 8e-4])
        near = table.near_wall(points, station, reach, slack)
        np.testing.assert_array_equal(near, _near_wall_numpy(table, points, station, reach,
                                                             slack))
        picked += len(near)
    assert 0 < picked < 200 * len(cells)     # some cells picked, not all


# --- the compiled kernels (foundation_kernels.py), each against a second route --------------

def _cells(count, seed):
    rng = np.random.default_rng(seed)
    r = rng.normal(scale=0.01, size=(count, 3))
    nu = rng.normal(size=(count, 3))
    nu /= np.linalg.norm(nu, axis=1)[:, None]
    return rng, r, nu, rng.uniform(0.0, 5.0, count), rng.uniform(0.0, 3.0, count)


def _jacobian(r):
    """A cell's velocity v + w x r as J [w; v] (3x6)."""
    x, y, z = r
    skew = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.hstack([-skew, np.eye(3)])


@pytest.mark.parametrize("seed", range(3))
def test_the_cells_response_is_the_sum_of_their_jacobians_gains(seed):
    from capsule_drake.physics.contact.foundation_kernels import response_gain
    _, r, nu, alpha, beta = _cells(40, seed)
    expected = sum(_jacobian(r[i]).T @ (beta[i] * np.eye(3) + (alpha[i] - beta[i])
                                        * np.outer(nu[i], nu[i])) @ _jacobian(r[i])
                   for i in range(len(r)))
    np.testing.assert_allclose(response_gain(r, nu, alpha, beta), expected, rtol=1e-12,
                               atol=1e-15)


@pytest.mark.parametrize("seed", range(3))
def test_the_implicit_step_is_the_dense_solve_then_coulombs_cone(seed):
    """implicit_wrench against NumPy: the velocity change dt A^-1 (F + other), each cell's
    force at the step's end, its friction clipped to mu times its pressing force."""
    from capsule_drake.physics.contact.foundation_kernels import implicit_wrench
    rng, r, nu, alpha, beta = _cells(30, seed)
    count, mu, dt, k_t, c_t = 30, 0.3, 2e-3, 50.0, 0.4
    pressed = rng.permutation(60)[:count]
    normal = rng.uniform(-0.01, 0.05, count)
    share = rng.uniform(0.0, 1.0, count)
    share /= share.sum()
    slip = rng.normal(scale=0.01, size=(count, 3))
    slip -= np.einsum("ij,ij->i", slip, nu)[:, None] * nu
    floor = -rng.uniform(0.0, 0.01, count)
    bristles = rng.normal(scale=1e-4, size=3 * 60)
    system = np.diag(rng.uniform(1e-6, 1e-2, 6)) + 1e-7 * np.ones((6, 6))
    other = rng.normal(scale=0.1, size=6)
    explicit, applied = implicit_wrench(pressed, r, nu, normal, alpha, beta, share, slip, floor,
                                        bristles, system, other, dt, mu, k_t, c_t)
    z = bristles.reshape(-1, 3)[pressed]
    z -= np.einsum("ij,ij->i", z, nu)[:, None] * nu
    tangential = (k_t * z + c_t * slip) * share[:, None]
    forces = normal[:, None] * nu - tangential

    def wrench(f):
        return np.r_[np.cross(r, f).sum(axis=0), f.sum(axis=0)]

    np.testing.assert_allclose(explicit, wrench(forces), rtol=1e-12, atol=1e-15)
    change = dt * np.linalg.solve(system, wrench(forces) + other)
    dv = change[3:] + np.cross(change[:3], r)
    dv_n = np.einsum("ij,ij->i", dv, nu)
    normal_end = np.maximum(normal - alpha * dv_n, floor)
    t_end = tangential + beta[:, None] * (dv - dv_n[:, None] * nu)
    size = np.linalg.norm(t_end, axis=1)
    limit = mu * np.maximum(normal_end, 0.0)
    over = size > limit
    t_end[over] *= (limit[over] / size[over])[:, None]
    assert over.any() and not over.all()       # both sides of the cone are exercised
    np.testing.assert_allclose(applied, wrench(normal_end[:, None] * nu - t_end), rtol=1e-9,
                               atol=1e-15)
