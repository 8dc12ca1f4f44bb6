"""The Vascular Modeling Toolkit's centreline beside our importer's, on the same tubes.

VMTK (PyPI `vmtk`) is the field's usual tool for a tube's centreline: the Voronoi diagram
of the closed surface, its poles' maximal inscribed spheres, and the path of least 1/R
cost between two seeds (vtkvmtkPolyDataCenterlines). It asks a person to click the ends;
here they are found without a click:
  - an open end is a boundary loop of the mesh (edges used by one face, joined into loops;
    the two largest by perimeter). The surface's holes are capped with a centre point each
    (vtkvmtkCapPolyData, as vmtkcenterlines does), and the cap centres are the seeds: as
    open profiles (the filter's CapCenterIds, vmtkcenterlines' `profileidlist`) when both
    ends are open;
  - a capped end is found on the surface: with both ends capped, the two vertices farthest
    apart along the surface (a double sweep over the edge graph: the vertex farthest from
    any vertex, then the vertex farthest from that one); with one end open, the vertex
    farthest from its loop. They are point seeds (vmtkcenterlines' `idlist`/`pointlist`),
    the open end's cap centre among them.
The seeds are appended to the line (vmtkcenterlines' `-endpoints 1`): at an open end the
section's centre, at a cap its far wall, which is where the true centreline ends (see
tests/tube_set.py). The line is resampled every 1 mm. The mesh is scaled to millimetres
for VMTK (its tolerances are in the mesh's unit or a share of its size) and back.

VMTK is not a dependency of the package: install it beside it, e.g.
    python -m pip install --no-deps --target vmtk-packages vmtk==1.5.2 vtk==9.6.2
and run with that folder on PYTHONPATH (its VTK and pydrake's, renamed inside libdrake,
share the process):
    PYTHONPATH=.:vmtk-packages python benchmarks/vmtk_route.py --tubes [--ours] [--csv F]
    PYTHONPATH=.:vmtk-packages python benchmarks/vmtk_route.py --sweep 60 --first-seed 20000 \
        --ours --csv F

--tubes runs on tests/tube_set.py's TUBES, --sweep N on N accepted random tubes from seed
--first-seed on (tube_set.random_spec; draws that make_tube refuses are skipped and not
counted, as in benchmarks/bench_import.py --sweep). Each tube prints and writes a row: the
largest distance from VMTK's line to the true one and from the true one to VMTK's (both
ways) [mm], their max, seconds, and a status; with --ours, the same for our importer
(capsule_drake.anatomy.imported.import_colon_mesh on the tube's file). The worst point's
place is given as the truth's end it is nearest (0 or 1) and its distance along the truth
from that end [mm]. A summary closes: within 2 mm, median, 90th percentile, worst.
"""

import argparse
import csv
import itertools
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from tube_set import TUBES, centreline_errors, densify, make_tube, random_spec  # noqa: E402

STEP_MM = 1.0
"""VMTK's resampling step along the line [mm]."""
JOIN_TOLERANCE_MM = 1.0
"""How far a line's end may be from its seed for the line to count as joining the ends."""
JITTERS = ((1e-3, "1 um"), (0.1, "0.1 mm"))
"""The random moves of every vertex [mm] VMTK is retried with when its line fails."""


# --- Finding the ends -----------------------------------------------------------------------

def boundary_loops(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    """The mesh's boundary loops (edges used by one face, joined where they share a vertex),
    each as its vertex indices, the longest (by perimeter) first."""
    edges = np.sort(mesh.edges, axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    if len(boundary) == 0:
        return []
    n = len(mesh.vertices)
    graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    edge_label = label[boundary[:, 0]]
    length = np.linalg.norm(mesh.vertices[boundary[:, 0]] - mesh.vertices[boundary[:, 1]], axis=1)
    loops = []
    for value in np.unique(edge_label):
        mine = edge_label == value
        loops.append((float(length[mine].sum()), np.unique(boundary[mine])))
    loops.sort(key=lambda item: -item[0])
    return [vertices for _, vertices in loops]


def edge_graph(mesh: trimesh.Trimesh):
    """The mesh's edges as a sparse graph weighted by their lengths."""
    edges = mesh.edges_unique
    n = len(mesh.vertices)
    return coo_matrix((mesh.edges_unique_length, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()


def farthest_vertex(graph, sources) -> int:
    """The vertex farthest along the surface from the nearest of `sources` (reachable ones)."""
    distance = dijkstra(graph, directed=False, indices=np.atleast_1d(sources), min_only=True)
    distance[~np.isfinite(distance)] = -1.0
    return int(np.argmax(distance))


def find_ends(mesh: trimesh.Trimesh):
    """The tube's two ends: a list of two (kind, data): ("open", loop vertex indices) or
    ("capped", a vertex index)."""
    loops = boundary_loops(mesh)
    if len(loops) >= 2:
        return [("open", loops[0]), ("open", loops[1])]
    graph = edge_graph(mesh)
    if len(loops) == 1:
        return [("open", loops[0]), ("capped", farthest_vertex(graph, loops[0]))]
    a = farthest_vertex(graph, 0)
    return [("capped", a), ("capped", farthest_vertex(graph, a))]


# --- VMTK -----------------------------------------------------------------------------------

def _polydata(vertices: np.ndarray, faces: np.ndarray):
    import vtk
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray

    points = vtk.vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(vertices, dtype=np.float64), deep=True))
    cells = vtk.vtkCellArray()
    offsets = np.arange(0, 3 * len(faces) + 1, 3, dtype=np.int64)
    cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_to_vtkIdTypeArray(np.ascontiguousarray(faces, dtype=np.int64).ravel(),
                                          deep=True))
    surface = vtk.vtkPolyData()
    surface.SetPoints(points)
    surface.SetPolys(cells)
    return surface


def _points(polydata) -> np.ndarray:
    from vtkmodules.util.numpy_support import vtk_to_numpy

    if polydata.GetPoints() is None:
        return np.zeros((0, 3))
    return vtk_to_numpy(polydata.GetPoints().GetData()).astype(float)


def vmtk_centreline(mesh: trimesh.Trimesh, step_mm: float = STEP_MM):
    """VMTK's centreline of a tube (mesh in metres) between its two ends, found without a
    click (see the module's text): ((K, 3) points in metres, status). The status is "ok",
    or says what went wrong: no line, more than one line (the longest is returned), or a
    line whose ends are not at the seeds (VMTK's path did not reach its target)."""
    points, status, _ = vmtk_centreline_seeds(mesh, step_mm)
    return points, status


def vmtk_centreline_seeds(mesh: trimesh.Trimesh, step_mm: float = STEP_MM):
    """vmtk_centreline's (points, status) and the two seeds (2, 3) [m].

    A regular triangulation has many vertices on a common sphere or plane, and VMTK's
    Delaunay tessellation (vtkDelaunay3D) then comes out degenerate: the descent along the
    Voronoi diagram stops short ("Degenerate descent detected. Target not reached."), or
    the diagram is empty (a circumsphere that cannot be solved for). A run whose line does
    not join its seeds is made again with every vertex moved at random by ~1 micrometre,
    and if that fails too by ~0.1 mm (as a user of VMTK would, or remesh); the status then
    says so."""
    work = trimesh.Trimesh(np.asarray(mesh.vertices, dtype=float) * 1000.0, mesh.faces,
                           process=True)  # mm; duplicate vertices merged
    ends = find_ends(work)
    points, status, seeds = _vmtk_line(work.vertices, work, ends, step_mm)
    tries = [status]
    for jitter, label in JITTERS:
        if tries[-1] == "ok":
            break
        moved = work.vertices + np.random.default_rng(0).normal(scale=jitter,
                                                                size=work.vertices.shape)
        again, second, seeds_again = _vmtk_line(moved, work, ends, step_mm)
        tries.append(second)
        if second == "ok" or len(again) > len(points):
            points, seeds = again, seeds_again
            status = second if second == "ok" else status
        if second == "ok":
            status = f"ok (jittered {label}; before: " + "; ".join(tries[:-1]) + ")"
    if tries[-1] != "ok":
        status = "; then ".join(tries) + " (as is, then jittered " + \
            ", ".join(label for _, label in JITTERS) + ")"
    return points / 1000.0, status, seeds / 1000.0


def _vmtk_line(vertices_mm, work, ends, step_mm):
    """One run of VMTK on the surface `work` (mm) with its vertices at `vertices_mm`:
    ((K, 3) points [mm], status, seeds (2, 3) [mm])."""
    import vtk
    from vmtk import vtkvmtk

    vtk.vtkObject.GlobalWarningDisplayOff()
    clean = vtk.vtkCleanPolyData()
    clean.SetInputData(_polydata(vertices_mm, work.faces))
    triangles = vtk.vtkTriangleFilter()
    triangles.SetInputConnection(clean.GetOutputPort())
    triangles.PassLinesOff()
    triangles.PassVertsOff()
    triangles.Update()
    surface = triangles.GetOutput()
    cap_ids = None
    if any(kind == "open" for kind, _ in ends):
        capper = vtkvmtk.vtkvmtkCapPolyData()
        capper.SetInputData(surface)
        capper.SetDisplacement(0.0)
        capper.SetInPlaneDisplacement(0.0)
        capper.Update()
        surface = capper.GetOutput()
        cap_ids = [capper.GetCapCenterIds().GetId(i)
                   for i in range(capper.GetCapCenterIds().GetNumberOfIds())]
    vertices = _points(surface)

    # Each end's seed: an open end's cap centre (the cap nearest its loop's mean), a capped
    # end's surface vertex (the capped surface's point nearest it).
    seeds, seed_points = [], []
    for kind, data in ends:
        if kind == "open":
            centre = vertices_mm[data].mean(axis=0)
            k = int(np.argmin(np.linalg.norm(vertices[cap_ids] - centre, axis=1)))
            seeds.append(("cap", k))
            seed_points.append(vertices[cap_ids[k]])
        else:
            point_id = int(cKDTree(vertices).query(vertices_mm[data])[1])
            seeds.append(("point", point_id))
            seed_points.append(vertices[point_id])

    centrelines = vtkvmtk.vtkvmtkPolyDataCenterlines()
    centrelines.SetInputData(surface)
    source, target = vtk.vtkIdList(), vtk.vtkIdList()
    if all(kind == "cap" for kind, _ in seeds):   # open profiles
        ids = vtk.vtkIdList()
        for cap in cap_ids:
            ids.InsertNextId(cap)
        centrelines.SetCapCenterIds(ids)
        source.InsertNextId(seeds[0][1])
        target.InsertNextId(seeds[1][1])
    else:                                         # point seeds on the (capped) surface
        for (kind, k), ids in zip(seeds, (source, target)):
            ids.InsertNextId(cap_ids[k] if kind == "cap" else k)
    centrelines.SetSourceSeedIds(source)
    centrelines.SetTargetSeedIds(target)
    centrelines.SetRadiusArrayName("MaximumInscribedSphereRadius")
    centrelines.SetCostFunction("1/R")
    centrelines.SetFlipNormals(0)
    centrelines.SetAppendEndPointsToCenterlines(1)
    centrelines.SetSimplifyVoronoi(0)
    centrelines.SetCenterlineResampling(0)   # resampled below, once its ends are checked
    centrelines.Update()
    output = centrelines.GetOutput()

    all_points = _points(output)
    lines = []
    for c in range(output.GetNumberOfCells()):
        ids = output.GetCell(c).GetPointIds()
        lines.append([ids.GetId(i) for i in range(ids.GetNumberOfIds())])
    lines = [line for line in lines if len(line) >= 2]
    seed_points = np.array(seed_points)
    if not lines:
        return np.zeros((0, 3)), "no line", seed_points
    longest = max(lines, key=lambda line: np.sum(np.linalg.norm(
        np.diff(all_points[line], axis=0), axis=1)))
    points = all_points[longest]
    status = []
    if len(lines) > 1:
        status.append(f"{len(lines)} lines")
    misses = [min(np.linalg.norm(points[0] - p), np.linalg.norm(points[-1] - p))
              for p in seed_points]
    if max(misses) > JOIN_TOLERANCE_MM:
        status.append("not joined (ends " + ", ".join(f"{m:.1f}" for m in misses) + " mm off)")
    elif len(points) >= 3:
        # The seeds are appended to the traced line: each lies on the maximal sphere of the
        # Voronoi point it is joined to, so the joining segment is about that sphere's
        # radius; a longer one bridges a descent that stopped short.
        from vtkmodules.util.numpy_support import vtk_to_numpy

        radius = vtk_to_numpy(output.GetPointData().GetArray("MaximumInscribedSphereRadius"))
        radius = radius[longest]
        for name, a, b in (("first", 0, 1), ("last", -1, -2)):
            jump = np.linalg.norm(points[a] - points[b])
            if jump > 1.5 * radius[b] + JOIN_TOLERANCE_MM:
                status.append(f"{name} seed joined by a {jump:.0f} mm jump")
    return resample(points, step_mm), "; ".join(status) or "ok", seed_points


def resample(points: np.ndarray, step: float) -> np.ndarray:
    """The polyline through `points` at even steps of about `step` along it, its ends kept."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    if s[-1] == 0.0:
        return points[:1]
    at = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / step)) + 1))
    return np.column_stack([np.interp(at, s, points[:, k]) for k in range(3)])


# --- Measuring ------------------------------------------------------------------------------

def worst_place(truth: np.ndarray, points: np.ndarray) -> str:
    """Where the worse of the two largest distances lies, as "E:D": the truth's end E (0 or 1)
    nearest it and the distance D [mm] along the truth from that end."""
    dense = densify(truth)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    to_truth, nearest = cKDTree(dense).query(points)
    to_line, _ = cKDTree(densify(points)).query(dense)
    at = s[nearest[np.argmax(to_truth)]] if to_truth.max() >= to_line.max() \
        else s[np.argmax(to_line)]
    end = 0 if at <= s[-1] - at else 1
    return f"{end}:{1000 * min(at, s[-1] - at):.0f}"


def vmtk_row(tube) -> dict:
    mesh = trimesh.Trimesh(tube.mesh.vertices * tube.scale, tube.mesh.faces, process=False)
    start = time.perf_counter()
    seeds = None
    try:
        points, status, seeds = vmtk_centreline_seeds(mesh)
    except Exception as e:  # noqa: BLE001 - any failure of the route is its result
        points, status = np.zeros((0, 3)), f"error: {type(e).__name__}: {str(e)[:80]}"
    seconds = time.perf_counter() - start
    row = _errors_row("vmtk", tube.truth, points, seconds, status)
    # How far the seeds found without a click lie from the true ends (0 and 1) [mm].
    if seeds is not None:
        ends = tube.truth[[0, -1]]
        off = np.linalg.norm(seeds[:, None, :] - ends[None, :, :], axis=2)  # seed x end
        pair = off[0, 0] + off[1, 1] <= off[0, 1] + off[1, 0]
        by_end = (off[0, 0], off[1, 1]) if pair else (off[1, 0], off[0, 1])
        row["vmtk_seed_off_mm"] = "/".join(f"{1000 * d:.1f}" for d in by_end)
    else:
        row["vmtk_seed_off_mm"] = ""
    return row


def ours_row(tube, folder) -> dict:
    from capsule_drake.anatomy.imported import import_colon_mesh

    path = tube.write(folder)
    start = time.perf_counter()
    try:
        wall = import_colon_mesh(path, tube.scale)
        points, status = wall.centerline.points, "ok"
    except ValueError as e:
        points, status = np.zeros((0, 3)), "refused: " + str(e).splitlines()[0][:100]
    seconds = time.perf_counter() - start
    path.unlink()
    return _errors_row("ours", tube.truth, points, seconds, status)


def _errors_row(route, truth, points, seconds, status) -> dict:
    if len(points) >= 2:
        to_truth, to_line = centreline_errors(truth, points)
        where = worst_place(truth, points)
    else:
        to_truth = to_line = np.inf
        where = ""
    return {f"{route}_to_truth_mm": round(1000 * to_truth, 2),
            f"{route}_to_line_mm": round(1000 * to_line, 2),
            f"{route}_max_mm": round(1000 * max(to_truth, to_line), 2),
            f"{route}_worst_at": where,
            f"{route}_s": round(seconds, 2), f"{route}_status": status}


def describe(spec) -> dict:
    return {"ends": "/".join(spec.ends), "mesh": spec.mesh, "faces": spec.faces,
            "unit": spec.unit, "flare": "/".join(f"{x:g}" for x in spec.flare),
            "oblique": "/".join(f"{x:g}" for x in spec.oblique),
            "end_bend": "/".join(f"{x:g}" for x in spec.end_bend),
            "haustra": spec.haustra, "ripple": spec.ripple}


def run(specs, label, ours: bool, csv_path, limit=None):
    """Runs the routes on the tubes that `specs` yields (name, spec), at most `limit` of them
    made, and prints/writes a row each; draws that make_tube refuses are skipped and not
    counted."""
    rows, skipped = [], 0
    routes = ["vmtk"] + (["ours"] if ours else [])
    header = f"{label:<20}{'ends':<22}" + "".join(
        f"{r + ' to truth/to line/max [mm]':>34}{'[s]':>7}  " for r in routes) + "status"
    print(header, flush=True)
    writer = handle = None
    with tempfile.TemporaryDirectory() as folder:
        for name, spec in specs:
            try:
                tube = make_tube(spec)
            except (RuntimeError, ValueError):
                skipped += 1
                continue
            row = {label: name, **describe(spec), "mesh_faces": len(tube.mesh.faces)}
            row.update(vmtk_row(tube))
            if ours:
                row.update(ours_row(tube, folder))
            rows.append(row)
            line = f"{name!s:<20}{row['ends']:<22}"
            for r in routes:
                line += (f"{row[r + '_to_truth_mm']:>12.2f}{row[r + '_to_line_mm']:>11.2f}"
                         f"{row[r + '_max_mm']:>11.2f}{row[r + '_s']:>7.1f}  ")
            print(line + " | ".join(f"{r}: {row[r + '_status']}" for r in routes), flush=True)
            if csv_path:
                if writer is None:
                    handle = open(csv_path, "w", newline="")
                    writer = csv.DictWriter(handle, fieldnames=list(row))
                    writer.writeheader()
                writer.writerow(row)
                handle.flush()
            if limit is not None and len(rows) >= limit:
                break
    if handle:
        handle.close()
    if skipped:
        print(f"({skipped} draws skipped: make_tube refused them)")
    for r in routes:
        e = np.array([row[r + "_max_mm"] for row in rows], dtype=float)
        seconds = np.array([row[r + "_s"] for row in rows], dtype=float)
        print(f"{r}: {len(e)} tubes, largest distance within 2 mm: {np.sum(e < 2.0)} of {len(e)}; "
              f"median {np.median(e):.2f} mm, 90th percentile {np.percentile(e, 90):.2f} mm, "
              f"worst {e.max():.2f} mm; wall time per tube median {np.median(seconds):.1f} s, "
              f"largest {seconds.max():.1f} s")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tubes", action="store_true", help="the 18 tubes of tests/tube_set.py")
    parser.add_argument("--sweep", type=int, default=0, metavar="N",
                        help="N accepted random tubes (tube_set.random_spec)")
    parser.add_argument("--first-seed", type=int, default=0, metavar="S")
    parser.add_argument("--ours", action="store_true", help="also run our importer on each tube")
    parser.add_argument("--csv", metavar="PATH", help="write the rows to this CSV")
    args = parser.parse_args()
    if args.tubes:
        run(((spec.name, spec) for spec in TUBES), "tube", args.ours, args.csv)
    elif args.sweep:
        seeds = itertools.count(args.first_seed)
        run(((seed, random_spec(seed)) for seed in seeds), "seed", args.ours, args.csv,
            limit=args.sweep)
    else:
        parser.error("give --tubes or --sweep N")


if __name__ == "__main__":
    main()
