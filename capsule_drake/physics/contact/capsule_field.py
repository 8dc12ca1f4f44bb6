"""The capsule's pressure field for the compliant wall: a tetrahedral mesh of the capsule,
fine around it and coarse along it.

Drake's compliant hydroelastic capsule is meshed evenly at its resolution hint; its pressure
is zero on the mesh's flat facets, which cut chords under the round surface. Against a wall
that yields by a millimetre or two the chords matter: at a 4 mm hint the force is 40 % low
at 0.5 mm of indentation, and a 1 mm hint that brings it within 5 % costs five times the
step. Along a cylinder the pressure does not change, so the mesh here is fine around (48
facets: chords 12 micrometres deep) and has two segments along the cylinder, every interior
vertex on the axis (as Drake's own capsule mesh: the pressure E (r - d) / r, linear from the
surface to the axis in every tetrahedron), and rings on the end caps. Written as a VTK file
once per shape in the colon cache's folder (anatomy/cache.py).
"""

import math
from pathlib import Path

import numpy as np

from capsule_drake.anatomy.cache import cache_base

AROUND = 48
"""Facets around the capsule: a chord 48 around a 5.8 mm radius lies 12 micrometres under
the surface, a hundredth of the indentations a run reaches."""
ALONG = 2
"""Segments along the cylinder: the pressure does not vary along it."""
CAP_RINGS = 6
"""Rings of vertices from the cylinder's edge to each cap's pole (15 degrees apart)."""


def capsule_field_tets(radius: float, length: float, around: int = AROUND,
                       along: int = ALONG, cap_rings: int = CAP_RINGS):
    """(vertices (V, 3), tetrahedra (T, 4)) of a capsule along z, its cylinder from -length/2
    to +length/2: interior vertices on its axis (the cylinder's stations and the caps'
    centres), surface vertices on a surface slightly outside the capsule's, by half a facet's
    chord depth, so that the facets lie as much outside the round surface as inside it (their
    mean radius is the capsule's); each tetrahedron positively oriented."""
    radius = radius * (1.0 + 0.5 * (1.0 - math.cos(math.pi / around)))
    vertices, tets = [], []
    stations = np.linspace(-0.5 * length, 0.5 * length, along + 1)
    axis = list(range(len(stations)))
    vertices += [[0.0, 0.0, z] for z in stations]
    phi = np.linspace(0.0, 2.0 * np.pi, around, endpoint=False)
    rings = []
    for z in stations:
        rings.append([len(vertices) + i for i in range(around)])
        vertices += [[radius * math.cos(p), radius * math.sin(p), z] for p in phi]
    for j in range(along):
        for i in range(around):
            k = (i + 1) % around
            a0, a1 = axis[j], axis[j + 1]
            p0, p1, q0, q1 = rings[j][i], rings[j][k], rings[j + 1][i], rings[j + 1][k]
            tets += [[a0, p0, p1, q1], [a0, p0, q1, q0], [a0, q0, q1, a1]]
    for side, centre, ring in ((1.0, axis[-1], rings[-1]), (-1.0, axis[0], rings[0])):
        z0 = vertices[centre][2]
        previous = ring
        for n in range(1, cap_rings + 1):
            theta = n * 0.5 * math.pi / cap_rings
            if n == cap_rings:
                pole = len(vertices)
                vertices.append([0.0, 0.0, z0 + side * radius])
                tets += [[centre, previous[i], previous[(i + 1) % around], pole]
                         for i in range(around)]
                break
            current = [len(vertices) + i for i in range(around)]
            vertices += [[radius * math.cos(theta) * math.cos(p),
                          radius * math.cos(theta) * math.sin(p),
                          z0 + side * radius * math.sin(theta)] for p in phi]
            for i in range(around):
                k = (i + 1) % around
                tets += [[centre, previous[i], previous[k], current[k]],
                         [centre, previous[i], current[k], current[i]]]
            previous = current
    vertices, tets = np.array(vertices), np.array(tets)
    a, b, c, d = (vertices[tets[:, i]] for i in range(4))
    negative = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) < 0.0
    tets[negative, 1], tets[negative, 2] = tets[negative, 2], tets[negative, 1].copy()
    return vertices, tets


def write_vtk(path: Path, vertices, tets) -> None:
    """A legacy-format VTK unstructured grid of tetrahedra (Drake reads it as a volume
    mesh), written to a temporary file and renamed."""
    lines = ["# vtk DataFile Version 3.0", "capsule pressure field mesh", "ASCII",
             "DATASET UNSTRUCTURED_GRID", f"POINTS {len(vertices)} double"]
    lines += [f"{x:.10g} {y:.10g} {z:.10g}" for x, y, z in vertices]
    lines.append(f"CELLS {len(tets)} {5 * len(tets)}")
    lines += [f"4 {a} {b} {c} {d}" for a, b, c, d in tets]
    lines.append(f"CELL_TYPES {len(tets)}")
    lines += ["10"] * len(tets)
    partial = path.with_name(f".{path.name}.partial")
    partial.write_text("\n".join(lines) + "\n")
    partial.replace(path)


def capsule_field_mesh(radius: float, length: float) -> Path:
    """The VTK file of `capsule_field_tets` for a capsule of this radius and cylinder length
    (m), made once in the colon cache's folder."""
    folder = cache_base() / "contact"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / (f"capsule_field_r{radius * 1e6:.0f}um_l{length * 1e6:.0f}um_"
                     f"{AROUND}x{ALONG}x{CAP_RINGS}m.vtk")
    if not path.exists():
        write_vtk(path, *capsule_field_tets(radius, length, AROUND, ALONG, CAP_RINGS))
    return path
