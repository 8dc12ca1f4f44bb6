"""Contact models compared: hydroelastic wall chunks vs convex wall pieces with point contact.

    .venv/bin/python benchmarks/bench_contact_models.py [--sim-seconds 5] [--repeats 3]
        [--sizes 0.010:0.0005 0.0125:0.001 ...]

A minimal plant: the capsule (models/capsule.sdf) and the default colon wall, 1 ms step,
`lagged` contact. A constant external force presses the capsule on the wall with 1 N (down,
plus its own weight) and drags it along the colon with 0.3 N, from the middle of the
transverse colon. Each model runs in its own process, so the peak memory (getrusage) is its own.
Printed per model: wall geometries, build time (wall geometry generation, then plant and diagram),
peak memory, real-time factor (median of the repeats), the capsule's largest excursion beyond
the analytic wall and how far it moved along the centreline.

The wall and the capsule's contact properties are registered exactly as the station does
(`capsule_drake.physics.contact.rigid.add_rigid_contact`), from a RigidWall
(physics/contact/rigid.py) whose `model` is "hydroelastic" or "convex_pieces".
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    ExternallyAppliedSpatialForce,
    MultibodyPlantConfig,
)
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource, VectorLogSink

from capsule_drake.anatomy import ColonParams, colon_wall_pieces, load_colon
from capsule_drake.capsule.model import CAPSULE_BODY, capsule_model, start_pose
from capsule_drake.io.metrics import capsule_poses, capsule_surface_points_C, wall_excursion
from capsule_drake.models import configure_parser, model_url
from capsule_drake.physics.contact import RigidWall
from capsule_drake.physics.contact.rigid import add_rigid_contact

START_S = 0.75            # middle of the default colon's transverse segment [m]
PRESS_N = 1.0             # external load toward the wall [N]
DRAG_N = 0.3              # external load along the colon [N]


def load_W(colon, s: float) -> np.ndarray:
    """Constant world force: PRESS_N down onto the wall, DRAG_N along the horizontal tangent."""
    tangent = colon.centerline.tangent_at(s).copy()
    tangent[2] = 0.0
    tangent /= np.linalg.norm(tangent)
    return DRAG_N * tangent + np.array([0.0, 0.0, -PRESS_N])


def build(model: str, colon, axial_length: float, chord_depth: float):
    """Diagram, capsule state logger and wall geometry count; times the two build stages."""
    contact = RigidWall(model="convex_pieces" if model == "pieces" else "hydroelastic",
                            piece_axial_length=axial_length, piece_max_chord_depth=chord_depth)
    start = time.perf_counter()
    if model == "pieces":  # generated once per process: timed on its own
        colon_wall_pieces(colon.params, contact.piece_axial_length,
                          contact.piece_max_chord_depth)
    geometry_seconds = time.perf_counter() - start

    start = time.perf_counter()
    builder = DiagramBuilder()
    config = MultibodyPlantConfig(time_step=1e-3, discrete_contact_approximation="lagged",
                                  use_sampled_output_ports=(model != "pieces"))
    plant, scene_graph = AddMultibodyPlant(config, builder)
    capsule_instance, = configure_parser(Parser(plant)).AddModels(
        url=model_url("capsule.sdf"))
    body = plant.GetBodyByName(CAPSULE_BODY)
    count = add_rigid_contact(plant, scene_graph, colon.params, colon, contact)
    plant.Finalize()
    plant.SetDefaultFloatingBaseBodyPose(body, start_pose(colon, START_S))

    force = ExternallyAppliedSpatialForce()
    force.body_index = body.index()
    force.p_BoBq_B = np.zeros(3)
    force.F_Bq_W = SpatialForce(np.zeros(3), load_W(colon, START_S))
    source = builder.AddSystem(ConstantValueSource(AbstractValue.Make([force])))
    builder.Connect(source.get_output_port(), plant.get_applied_spatial_force_input_port())
    logger = builder.AddSystem(VectorLogSink(13, publish_period=0.01))
    builder.Connect(plant.get_state_output_port(capsule_instance), logger.get_input_port())
    diagram = builder.Build()
    return diagram, logger, count, geometry_seconds, time.perf_counter() - start


def run_one(model: str, axial_length: float, chord_depth: float, sim_seconds: float,
            repeats: int) -> dict:
    # The colon and its mesh files, built (or read from the cache) once: not part of the
    # build (the wall pieces are generated from this colon, timed, in build()).
    colon, _ = load_colon(ColonParams())
    diagram, logger, count, geometry_s, build_s = build(model, colon, axial_length,
                                                        chord_depth)
    factors = []
    for _ in range(repeats):
        simulator = Simulator(diagram)
        simulator.Initialize()
        start = time.perf_counter()
        simulator.AdvanceTo(sim_seconds)
        factors.append(sim_seconds / (time.perf_counter() - start))
    log = logger.FindLog(simulator.get_context())
    R_WC, p_WC = capsule_poses(log.data())
    capsule = capsule_model()
    excursion = wall_excursion(colon, R_WC, p_WC,
                               capsule_surface_points_C(capsule.radius, capsule.length, 24))
    s, _, _ = colon.centerline.closest(p_WC)
    settled = log.sample_times() >= 0.5  # after the drop from the centreline onto the wall
    return {
        "model": model, "axial_mm": 1e3 * axial_length, "chord_mm": 1e3 * chord_depth,
        "geometries": count, "geometry_s": geometry_s, "build_s": build_s,
        "peak_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "rtf": statistics.median(factors), "rtf_runs": factors,
        "excursion_mm": 1e3 * float(np.max(excursion)),
        "settled_excursion_mm": 1e3 * float(np.max(excursion[settled])),
        "clearance_mm": -1e3 * float(np.median(excursion[settled])),
        "moved_mm": 1e3 * float(s[-1] - s[0]),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim-seconds", type=float, default=5.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sizes", nargs="*", default=["0.0125:0.001", "0.010:0.0005"],
                        help="piece sizes as axial_length:max_chord_depth [m]")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        model, axial, chord = args.one.split(":")
        print(json.dumps(run_one(model, float(axial), float(chord), args.sim_seconds,
                                 args.repeats)))
        return

    jobs = ["hydroelastic:0:0"] + [f"pieces:{size}" for size in args.sizes]
    print(f"{args.sim_seconds:.0f} s at 1 ms, lagged; {PRESS_N} N onto the wall, {DRAG_N} N "
          f"along it; RTF = median of {args.repeats}")
    print(f"{'model':<13}{'axial mm':>9}{'chord mm':>9}{'geoms':>7}{'gen s':>7}{'build s':>8}"
          f"{'peak GB':>8}{'RTF':>6}{'excursion mm':>13}{'settled':>8}{'clear mm':>9}"
          f"{'moved mm':>9}")
    for job in jobs:
        out = subprocess.run([sys.executable, __file__, "--one", job,
                              "--sim-seconds", str(args.sim_seconds),
                              "--repeats", str(args.repeats)],
                             capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{r['model']:<13}{r['axial_mm']:>9.1f}{r['chord_mm']:>9.2f}{r['geometries']:>7d}"
              f"{r['geometry_s']:>7.1f}{r['build_s']:>8.1f}{r['peak_gb']:>8.2f}{r['rtf']:>6.1f}"
              f"{r['excursion_mm']:>13.2f}{r['settled_excursion_mm']:>8.2f}"
              f"{r['clearance_mm']:>9.2f}{r['moved_mm']:>9.1f}", flush=True)


if __name__ == "__main__":
    main()
