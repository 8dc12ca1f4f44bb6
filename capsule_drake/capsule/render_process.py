"""The render worker's process (`python -m capsule_drake.capsule.render_process`): draws a
capsule camera's frames on another core (capsule/render_worker.py has the protocol and the
camera's side)."""

import pickle
import sys

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.anatomy import load_colon
from capsule_drake.capsule.camera_renderer import LensRenderer
from capsule_drake.capsule.camera_walls import add_camera_walls
from capsule_drake.capsule.render_worker import (POSE_BYTES, read_message,
                                                 write_message)


def serve(stdin, stdout) -> None:
    """The worker's loop (module docstring), on binary streams."""
    try:
        colon_params, config = pickle.loads(read_message(stdin))
        builder = DiagramBuilder()
        plant, scene_graph = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.0), builder)
        walls = add_camera_walls(plant, scene_graph, colon_params, load_colon(colon_params)[0],
                                 config)
        plant.Finalize()
        diagram = builder.Build()
        context = diagram.CreateDefaultContext()
        query = scene_graph.get_query_output_port().Eval(
            scene_graph.GetMyContextFromRoot(context))
        world = query.inspector().world_frame_id()
        renderer = LensRenderer(config)
        image = np.empty((renderer.height, renderer.width, 4), dtype=np.uint8)
        write_message(stdout, b"ready")
        while True:
            message = read_message(stdin)
            if len(message) != POSE_BYTES:
                raise ValueError(f"a pose message of {len(message)} bytes, not {POSE_BYTES}")
            pose = np.frombuffer(message, dtype="<f8")
            X_WC = RigidTransform(RotationMatrix(pose[:9].reshape(3, 3)), pose[9:])
            renderer.render_rgba(query, world, X_WC, out=image, renderer=walls(pose[9:]))
            write_message(stdout, image)
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        pass
    except Exception as e:  # reported to the camera, which then draws its own frames
        try:
            write_message(stdout, f"{type(e).__name__}: {e}".encode()[:1000])
        except OSError:
            pass


if __name__ == "__main__":
    serve(sys.stdin.buffer, sys.stdout.buffer)
