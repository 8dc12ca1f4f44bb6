"""The colon wall as capsule cameras see it (`add_camera_walls`), and the block
`capsule.camera_walls` that puts it in the scene before the plant is finalised: windows of
the wall, each with a renderer of its own, and the lesions with render labels of their own.
"""

import dataclasses
from pathlib import Path

import numpy as np
from pydrake.geometry import GeometryInstance, Mesh, PerceptionProperties, RenderLabel, Rgba, Role
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser

from capsule_drake.anatomy import colon_assets
from capsule_drake.anatomy.lumen_state import BUBBLE_RGBA, FLUID_RGBA
from capsule_drake.anatomy.source import fluid_scene, lesion_scene
from capsule_drake.anatomy.windows import CameraWindows, camera_windows
from capsule_drake.blocks import block
from capsule_drake.capsule.camera_config import CameraConfig
from capsule_drake.capsule.camera_renderer import add_camera_renderer

LESION_LABEL_BASE = 1000
"""The render label of polyp k is LESION_LABEL_BASE + k (the plant's own labels are body
indices, far below)."""


@dataclasses.dataclass
class CameraWalls:
    """The camera windows and their renderers; called with a camera's world position, it
    names the renderer to draw with (the window of the centreline foot's arc length)."""

    windows: CameraWindows
    renderer_names: list[str]
    centerline: object

    def __call__(self, p_WC) -> str:
        s = self.centerline.closest(np.asarray(p_WC, dtype=float))[0]
        return self.renderer_names[self.windows.index_at(s)]


def add_camera_walls(plant, scene_graph, colon_params, colon,
                     config: CameraConfig) -> CameraWalls:
    """The colon wall as capsule cameras see it, and their renderers. Call before Finalize,
    after every other model: the cameras see nothing else (the geometry registered so far
    loses its perception role).

    Each window is accepted by a renderer of its own (`<config.renderer_name>.<k>`, added
    here), so a frame draws only the stretch the camera is in. Returns the `CameraWalls`
    that names the renderer for a camera at p_WC; another camera in the colon sees the wall
    through it.
    """
    assets = colon_assets(colon_params)
    windows = camera_windows(colon, assets.visual_obj.parent, config.far,
                             config.window_spacing)
    if len(windows.objs) == 1:
        names = [config.renderer_name]
    else:
        names = [f"{config.renderer_name}.{k:02d}" for k in range(len(windows.objs))]
    for name in names:
        add_camera_renderer(scene_graph, config, name)
    visuals = [(f"window_{k:02d}", obj, name)
               for k, (obj, name) in enumerate(zip(windows.objs, names))]
    # pydrake cannot set the ("renderer", "accepting") property (a set of names), so the
    # walls come as an SDF model with <drake:accepting_renderer> tags.
    body = "".join(
        f"<visual name='{name}'><geometry><mesh><uri>{Path(obj).resolve().as_uri()}</uri>"
        f"</mesh></geometry><drake:accepting_renderer>{renderer}</drake:accepting_renderer>"
        "</visual>" for name, obj, renderer in visuals)
    fluid = fluid_scene(colon_params)
    accepting = "".join(f"<drake:accepting_renderer>{name}</drake:accepting_renderer>"
                        for name in names)
    for name, path, colour in (("fluid_surface", fluid.surface_obj, FLUID_RGBA),
                               ("fluid_bubbles", fluid.bubbles_obj, BUBBLE_RGBA)):
        if path is None:   # the liquid's surface and bubbles (colon.lumen), in every window
            continue
        rgba = " ".join(f"{c:g}" for c in colour)
        body += (f"<visual name='{name}'><geometry><mesh><uri>{path.resolve().as_uri()}"
                 f"</uri></mesh></geometry><material><diffuse>{rgba}</diffuse></material>"
                 f"{accepting}</visual>")
    sdf = ("<?xml version='1.0'?><sdf version='1.9' xmlns:drake='http://drake.mit.edu'>"
           f"<model name='camera_walls_{config.renderer_name}'><static>true</static>"
           f"<link name='walls'>{body}"
           "</link></model></sdf>")
    instance, = Parser(plant).AddModelsFromString(sdf, "sdf")
    for index in plant.GetBodyIndices(instance):
        for geometry_id in plant.GetVisualGeometriesForBody(plant.get_body(index)):
            scene_graph.RemoveRole(plant.get_source_id(), geometry_id, Role.kIllustration)
    # A capsule camera sees only the inside of the colon. Everything else (the capsule's own
    # shell, the EPM, the arm, the table) would sit in every window's renderer, unseen, and
    # each renderer re-poses its moving geometry at every physics step: with the arm's links
    # in 16 renderers that cost ~1.5 s per simulated second (measured), more than drawing.
    inspector = scene_graph.model_inspector()
    source = plant.get_source_id()
    for geometry_id in inspector.GetAllGeometryIds(Role.kPerception):
        if not inspector.BelongsToSource(geometry_id, source):
            continue
        body = plant.GetBodyFromFrameId(inspector.GetFrameId(geometry_id))
        if not plant.GetModelInstanceName(body.model_instance()).startswith("camera_walls_"):
            scene_graph.RemoveRole(source, geometry_id, Role.kPerception)
    # Then each polyp on the world body (anchored: a renderer never re-poses it) with a
    # render label of its own, so that the label image is each lesion's instance mask.
    # Every renderer draws them (pydrake cannot name accepting renderers); a later camera's
    # walls strip them above and register them again, so there is one set whatever the
    # number of cameras. (Links of their own would give them their bodies' labels, but a
    # body's geometry is re-posed in every renderer at every step: Navigation's real-time
    # factor fell 37 %.)
    # A diverticulum's sac likewise (its neck's collar is part of the wall), in the mucosa's
    # own colour.
    lesions = lesion_scene(colon_params)
    sac_colour = Rgba(*colon_params.mucosa.base_color, 1.0)
    # A polyp's look is its surface's own material and texture (anatomy/lesion_texture.py).
    for lesion, path, colour, kind in (
            [(p, o, None, "polyp") for p, o in zip(lesions.polyps, lesions.surface_objs)]
            + [(d, o, sac_colour, "diverticulum")
               for d, o in zip(lesions.diverticula, lesions.sac_objs)]):
        name = f"{kind}_label_{lesion.index:03d}"
        properties = PerceptionProperties()
        if colour is not None:
            properties.AddProperty("phong", "diffuse", colour)
        properties.AddProperty("label", "id", RenderLabel(LESION_LABEL_BASE + lesion.index))
        geometry = GeometryInstance(RigidTransform(), Mesh(str(path)), name)
        geometry.set_perception_properties(properties)
        plant.RegisterVisualGeometry(plant.world_body(), geometry)
    return CameraWalls(windows, names, colon.centerline)


def lesion_labels(lesions) -> dict[int, int]:
    """{render label: lesion index} of placed polyps (anatomy/lesion_geometry.py) or
    diverticula (anatomy/diverticula.py) in a camera's label image (`add_camera_walls`
    labels them)."""
    return {LESION_LABEL_BASE + p.index: p.index for p in lesions}


def add_camera_wall_models(parts, config: CameraConfig):
    """Before Finalize, after every other model (the camera sees only these walls): the
    capsule camera's walls and renderers (`add_camera_walls`); sets parts.renderer_for."""
    parts.renderer_for = add_camera_walls(parts.plant, parts.scene_graph, parts.colon_params,
                                          parts.colon, config)


block("capsule.camera_walls", CameraConfig, key="capsule.camera",
      models=add_camera_wall_models)(None)
