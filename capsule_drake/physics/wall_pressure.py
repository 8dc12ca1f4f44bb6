"""Pressure on the colon wall where it acts: a map of the wall's patches, each with its peak
contact pressure and the longest time it spent above each threshold of physics/tissue.py.

The thresholds are stated for one place of the tissue: 330 kPa pressed for seconds
(mucosal injury), 30 mmHg (4.0 kPa) held for minutes (the wall's blood flow falls). A
capsule dragged along the colon presses each place for a second or two; the run's summed
time above a threshold (io/metrics.py `pressure_metrics`) adds up every place it passed.
Here the wall is cut into patches (PATCH_LENGTH of arc length along the centreline by
360 / PATCHES_AROUND degrees around it, the angle theta measured as the colon's own
`wall_radius(s, theta)` measures it: in the centreline's frame at s, from the normal toward
the binormal), and each patch keeps its own figures.

- `face_peaks`, `patch_index`, `patch_peaks`, `accumulate`: the mapping, pure (numpy in,
  numpy out): a contact surface's faces, each located at its centroid and carrying its
  vertices' largest pressure (the field is linear on a face, so that is the face's
  largest), become the patches' pressures of one sample; the samples accumulate into
  peaks and spells above the thresholds.
- `contact_faces`: a plant's ContactResults as those faces (Drake's ContactSurface API);
  the only part that touches Drake's types.
- `WallPressureMap`: the LeafSystem that samples the contact every SAMPLE_PERIOD in a
  periodic update of its own state (its map is state in the context: a run is
  deterministic; it reads only the contact results, changing nothing of the simulation);
  `wall_pressure(context)` gives the map as a `WallPressure`.

Point contact (the convex-pieces wall) has no pressure field: the map is then empty and
says so (`WallPressure.has_pressure` False), never a made-up figure.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.plant import ContactResults

from capsule_drake.physics.contact.foundation import empty_wall_contact
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from scipy.spatial import cKDTree

from capsule_drake.physics.tissue import PRESSURE_THRESHOLDS

PATCH_LENGTH = 0.01
"""m of arc length along the centreline per patch: a capsule's contact (a few mm long) sits
in one or two; the capsule (31.5 mm long with its domes) spans three or four."""

PATCHES_AROUND = 12
"""Patches around the wall (30 degrees each: 10-15 mm of a 20-30 mm lumen radius, the size of
a patch along it)."""

SAMPLE_PERIOD = 0.01
"""s between samples of the contact. The thresholds are for presses of seconds (injury) and
minutes (ischaemia); a capsule dragged at ~1 cm/s crosses a 1 cm patch in about a second,
so 10 ms times a spell to about 1 %. It is the runs' default log period, and the map reads
the state the loggers read at the same times: its samples are logs.npz's contact_pressure
samples (all but the last, at the run's end), so its peak is their largest
(tests/test_wall_pressure.py). Cost per sample: benchmarks/bench_wall_pressure.py
(docs/models/contact.md, "Tissue safety")."""

WALL_PRESSURE_SYSTEM = "wall_pressure"
"""The run's wall-pressure map beside the station (app/run.py)."""


# --- The mapping, pure -----------------------------------------------------------------------

def face_peaks(face_data, vertex_pressures) -> np.ndarray:
    """The largest vertex pressure of each face of a polygon mesh given as Drake's flat
    `face_data` ([n0, v0_0 .. v0_n0-1, n1, v1_0 ...]: each face's vertex count, then its
    vertex indices). Returns (F,)."""
    data = face_data.tolist() if isinstance(face_data, np.ndarray) else list(face_data)
    values = np.asarray(vertex_pressures, dtype=float)
    indices, starts, k = [], [], 0
    while k < len(data):
        n = data[k]
        starts.append(len(indices))
        indices += data[k + 1:k + 1 + n]
        k += n + 1
    if not starts:
        return np.zeros(0)
    return np.maximum.reduceat(values[indices], starts)


@dataclasses.dataclass(frozen=True)
class PatchGrid:
    """The wall's patches: `n_along` bins of arc length (edges 0, length, 2 length, ...,
    the last one ending at the colon's end) by `n_around` bins of theta from 0 to 2 pi.
    Patch (i, j) is flat index i * n_around + j."""

    colon_length: float
    length: float = PATCH_LENGTH
    n_around: int = PATCHES_AROUND

    @functools.cached_property
    def n_along(self) -> int:
        return max(1, int(np.ceil(self.colon_length / self.length - 1e-9)))

    @functools.cached_property
    def size(self) -> int:
        return self.n_along * self.n_around

    @property
    def shape(self) -> tuple[int, int]:
        return self.n_along, self.n_around

    @property
    def s_edges(self) -> np.ndarray:
        edges = np.arange(self.n_along + 1) * self.length
        edges[-1] = self.colon_length
        return edges

    @property
    def theta_edges(self) -> np.ndarray:
        return np.linspace(0.0, 2.0 * np.pi, self.n_around + 1)


def patch_index(s, theta, grid: PatchGrid) -> np.ndarray:
    """Flat patch index of wall points at arc length s (m; clipped to the colon) and angle
    theta (rad, any turn)."""
    s, theta = np.asarray(s, dtype=float), np.asarray(theta, dtype=float)
    # (np.minimum and np.maximum: np.clip costs several times as much on a few dozen.)
    i = np.minimum(np.maximum(np.floor(s / grid.length), 0), grid.n_along - 1).astype(np.int64)
    j = np.minimum(np.floor(np.mod(theta, 2.0 * np.pi) * (grid.n_around / (2.0 * np.pi))),
                   grid.n_around - 1).astype(np.int64)
    return i * grid.n_around + j


def patch_peaks(index, pressure, size: int) -> np.ndarray:
    """The largest of the pressures (Pa) falling in each of `size` patches (flat `index`);
    0 where none falls."""
    out = np.zeros(size)
    if len(index):
        np.maximum.at(out, np.asarray(index, dtype=np.int64), np.asarray(pressure, dtype=float))
    return out


def accumulate(peak, start, longest, sample, t: float, thresholds):
    """One sample into the map: returns (peak, start, longest) updated, new arrays.

    Args:
        peak: (P,) each patch's peak pressure so far (Pa).
        start: (T, P) for each threshold, when the patch's current spell above it began (s;
            NaN: below it).
        longest: (T, P) each patch's longest spell above each threshold so far (s).
        sample: (P,) the patches' pressures at time t (Pa; 0 where untouched).
        t: the sample's time (s).
        thresholds: (T,) Pa; "above" is strictly above.

    A sample's value holds until the next sample (as physics/tissue.py `time_above`): a
    spell that begins at the sample at t_a and ends at the first sample below, t_b, lasted
    t_b - t_a; one still going at the last sample counts up to it. A patch that drops below
    a threshold starts again from zero.
    """
    sample = np.asarray(sample, dtype=float)
    thresholds = np.asarray(thresholds, dtype=float).reshape(-1, 1)
    start, longest = np.asarray(start, dtype=float), np.asarray(longest, dtype=float)
    above = sample[None, :] > thresholds
    going = ~np.isnan(start)
    begun = np.where(above, np.where(going, start, t), np.nan)
    # A spell ending now lasted up to now, as has one still going (so far).
    spell = np.where(above, t - begun, np.where(going, t - start, 0.0))
    return np.maximum(peak, sample), begun, np.maximum(longest, spell)



class WallLocator:
    """Where wall points are along and around a Centerline, fast: (s, theta) as its
    `closest` gives them (theta from the frame's normal toward its binormal), from the
    nearest of its samples (~1 mm apart) and one Newton step of the foot point along the
    sample's osculating parabola, the frame taken at that sample. Within 0.01 mm and 0.05
    degree of `closest` on wall points up to 2/3 of a bend's radius from the axis (a colon
    bends no tighter than 1.5 lumen radii; tests/test_wall_pressure.py), at a fifth of its
    cost for a contact's few dozen faces (0.07 against 0.31 ms for 37, measured): `closest`
    iterates Newton on the spline, whose evaluations dominate at this size."""

    def __init__(self, centerline):
        self.s = np.asarray(centerline.s, dtype=float)
        self.points = np.asarray(centerline.points, dtype=float)
        tangents = np.asarray(centerline.tangents, dtype=float)
        # x''(s) at the samples, from the tangents' change (the curve is in arc length).
        curvature = np.gradient(tangents, self.s, axis=0)
        # Per sample, the directions a point's offset is projected on: (N, 3, 4).
        self._basis = np.stack([tangents, curvature, np.asarray(centerline.normals, float),
                                np.asarray(centerline.binormals, float)], axis=2)
        self._tree = cKDTree(self.points)

    def locate(self, points) -> tuple[np.ndarray, np.ndarray]:
        """(s (m, clipped to the centreline), theta (rad, in (-pi, pi])) of points (K, 3)."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        _, k = self._tree.query(p)
        d = p - self.points[k]
        # d . t, d . x'', d . n, d . b (n and b are normal to t: d's radial part's too).
        along, bent, dn, db = np.einsum("ij,ijk->ki", d, self._basis[k])
        # Newton on f(u) = (x(s_k + u) - p) . x'(s_k + u) = 0 from u = 0.
        slope = 1.0 - bent
        u = along / np.where(slope > 0.2, slope, 1.0)
        s = np.minimum(np.maximum(self.s[k] + u, self.s[0]), self.s[-1])
        return s, np.arctan2(db, dn)


# --- Drake's contact, as faces ---------------------------------------------------------------

def contact_faces(results) -> tuple[np.ndarray, np.ndarray, int]:
    """The pressed faces of a plant's ContactResults: (centroids (F, 3) in world, m; each
    face's largest pressure (F,), Pa: its vertices' largest, from the surface's pressure
    field e_MN; the number of point contacts, which have no pressure). Faces whose pressure
    is 0 everywhere (the surface's rim) are left out."""
    centroids, peaks = [], []
    for i in range(results.num_hydroelastic_contacts()):
        surface = results.hydroelastic_contact_info(i).contact_surface()
        if surface.is_triangle():
            mesh, field = surface.tri_mesh_W(), surface.tri_e_MN()
            face_data = []
            for triangle in mesh.triangles():
                face_data += [3, triangle.vertex(0), triangle.vertex(1), triangle.vertex(2)]
        else:
            mesh, field = surface.poly_mesh_W(), surface.poly_e_MN()
            face_data = mesh.face_data()
        values = [field.EvaluateAtVertex(v) for v in range(mesh.num_vertices())]
        peak = face_peaks(face_data, values)
        pressed = np.flatnonzero(peak > 0.0)
        centroids += [mesh.element_centroid(f) for f in pressed.tolist()]
        peaks.append(peak[pressed])
    points = np.array(centroids, dtype=float).reshape(-1, 3)
    return points, (np.concatenate(peaks) if peaks else np.zeros(0)), \
        results.num_point_pair_contacts()


def capsule_has_pressure_field(plant, scene_graph, body_name: str) -> bool:
    """Whether the collision geometries of the plant's body `body_name` that take part in
    contact (a proximity role) are hydroelastic (they have a compliance type): only then does
    its contact carry a pressure field. (A station's runs ask the contact model instead:
    its `pressure_field`.)"""
    inspector = scene_graph.model_inspector()
    body = plant.GetBodyByName(body_name)
    touching = [inspector.GetProximityProperties(g)
                for g in plant.GetCollisionGeometriesForBody(body)]
    touching = [p for p in touching if p is not None]
    return bool(touching) and all(p.HasProperty("hydroelastic", "compliance_type")
                                  for p in touching)


# --- The map ---------------------------------------------------------------------------------

@dataclasses.dataclass
class WallPressure:
    """The wall's patches and what each went through (`WallPressureMap`'s state, read).

    grid: the PatchGrid. peak: (n_along, n_around) each patch's peak pressure (Pa).
    longest_above: threshold name -> (n_along, n_around) the longest spell the patch spent
    above it (s). thresholds: name -> Pa. samples: how many samples were taken, the first
    and last at first_time and last_time (s; NaN without any), every `period` s.
    point_contact_samples: samples that found point contacts (no pressure).
    pressure_field: whether the capsule's contact has a pressure field at all.
    """

    grid: PatchGrid
    peak: np.ndarray
    longest_above: dict
    thresholds: dict
    samples: int = 0
    point_contact_samples: int = 0
    pressure_field: bool = True
    period: float = SAMPLE_PERIOD
    first_time: float = float("nan")
    last_time: float = float("nan")

    @property
    def has_pressure(self) -> bool:
        """Whether the map holds pressures: a pressure field, sampled, and no contact
        without a pressure (then its figures would leave that contact out)."""
        return self.pressure_field and self.samples > 0 and self.point_contact_samples == 0

    def patch_centre(self, i: int, j: int) -> tuple[float, float]:
        """(s (m), theta (deg)) at the centre of patch (i along, j around)."""
        s = self.grid.s_edges
        return 0.5 * (s[i] + s[i + 1]), (j + 0.5) * 360.0 / self.grid.n_around

    def arrays(self) -> dict:
        """The map as named arrays (wall_pressure.npz): s_edges_m, theta_edges_deg,
        peak_pressure_kPa and longest_above_<name>_s (n_along x n_around; NaN without a
        pressure), threshold_<name>_kPa, samples, point_contact_samples, pressure_field,
        period_s, first_time_s, last_time_s."""
        blank = np.full(self.grid.shape, np.nan)
        out = {"s_edges_m": self.grid.s_edges,
               "theta_edges_deg": np.degrees(self.grid.theta_edges),
               "peak_pressure_kPa": self.peak / 1000.0 if self.has_pressure else blank}
        for name, value in self.thresholds.items():
            out[f"longest_above_{name}_s"] = (self.longest_above[name] if self.has_pressure
                                              else blank)
            out[f"threshold_{name}_kPa"] = np.float64(value / 1000.0)
        out.update(samples=np.int64(self.samples),
                   point_contact_samples=np.int64(self.point_contact_samples),
                   pressure_field=np.bool_(self.pressure_field), period_s=np.float64(self.period),
                   first_time_s=np.float64(self.first_time),
                   last_time_s=np.float64(self.last_time))
        return out

    @classmethod
    def from_arrays(cls, arrays) -> "WallPressure":
        """The map `arrays()` wrote (e.g. np.load of wall_pressure.npz)."""
        s_edges = np.asarray(arrays["s_edges_m"], dtype=float)
        n_around = len(arrays["theta_edges_deg"]) - 1
        length = float(s_edges[1] - s_edges[0]) if len(s_edges) > 2 else float(s_edges[-1])
        grid = PatchGrid(float(s_edges[-1]), length, n_around)
        names = [key[len("threshold_"):-len("_kPa")] for key in arrays
                 if key.startswith("threshold_")]
        return cls(grid, np.asarray(arrays["peak_pressure_kPa"], dtype=float) * 1000.0,
                   {name: np.asarray(arrays[f"longest_above_{name}_s"], dtype=float)
                    for name in names},
                   {name: float(arrays[f"threshold_{name}_kPa"]) * 1000.0 for name in names},
                   int(arrays["samples"]), int(arrays["point_contact_samples"]),
                   bool(arrays["pressure_field"]), float(arrays["period_s"]),
                   float(arrays["first_time_s"]), float(arrays["last_time_s"]))


@dataclasses.dataclass(frozen=True)
class MapLayout:
    """How `WallPressureMap` lays its map out in its state vector: [peak (P) | start (T x P)
    | longest (T x P) | samples, point-contact samples, first sample's time, last sample's
    time], P patches of `grid`, T `thresholds` (name -> Pa). `map_of` reads such a vector
    (the system's `map` output, e.g. in an MCAP logger) without the system."""

    grid: PatchGrid
    thresholds: tuple  # ((name, Pa), ...)
    pressure_field: bool = True
    period: float = SAMPLE_PERIOD

    @property
    def size(self) -> int:
        return self.grid.size * (1 + 2 * len(self.thresholds)) + 4

    def initial(self) -> np.ndarray:
        """No sample yet: peaks and spells 0, no spell going (NaN starts), no times."""
        P, T = self.grid.size, len(self.thresholds)
        x = np.zeros(self.size)
        x[P:P + T * P] = np.nan
        x[-2:] = np.nan
        return x

    def split(self, x):
        """(peak (P,), start (T, P), longest (T, P), [samples, point samples, first, last])
        of a state vector (views)."""
        P, T = self.grid.size, len(self.thresholds)
        return (x[:P], x[P:P + T * P].reshape(T, P), x[P + T * P:P + 2 * T * P].reshape(T, P),
                x[-4:])

    def map_of(self, x) -> WallPressure:
        """The WallPressure a state vector holds."""
        peak, _, longest, counts = self.split(np.asarray(x, dtype=float))
        shape = self.grid.shape
        return WallPressure(self.grid, peak.reshape(shape).copy(),
                            {name: longest[k].reshape(shape).copy()
                             for k, (name, _) in enumerate(self.thresholds)},
                            dict(self.thresholds), int(counts[0]), int(counts[1]),
                            self.pressure_field, self.period, float(counts[2]),
                            float(counts[3]))


class WallPressureMap(LeafSystem):
    """Samples the plant's contact every `period` s (a periodic update from t = 0)
    and keeps, per patch of the wall (`PatchGrid` of the colon), its peak pressure and, per
    threshold (physics/tissue.py: injury 330 kPa, ischaemia 4.0 kPa), when its current
    spell above began and its longest spell so far (`accumulate`); the module docstring
    says how a face is put on a patch. Its state is its own: it reads the contact results
    and changes nothing else.

    .. pydrake_system::

        name: WallPressureMap
        input_ports:
        - contact_results
        output_ports:
        - map

    map: the state vector (`layout` reads it; `wall_pressure(context)` gives the map).

    Args:
        centerline: the colon's Centerline (its samples and frames: `WallLocator`).
        pressure_field: whether the contact has a pressure field (false: point contact;
            nothing is sampled and the map says it has no pressure).
        period: s between samples.
        grid: the patches (default: PATCH_LENGTH by PATCHES_AROUND over the centreline).
        thresholds: name -> Pa (default physics/tissue.py PRESSURE_THRESHOLDS).
    """

    def __init__(self, centerline, pressure_field: bool = True, period: float = SAMPLE_PERIOD,
                 grid: PatchGrid | None = None, thresholds=None, wall: bool = False):
        super().__init__()
        self._locator = WallLocator(centerline)
        self.layout = MapLayout(grid or PatchGrid(float(centerline.length)),
                                tuple(dict(thresholds or PRESSURE_THRESHOLDS).items()),
                                bool(pressure_field), float(period))
        self._levels = np.array([value for _, value in self.layout.thresholds], dtype=float)
        self._state = self.DeclareDiscreteState(BasicVector(self.layout.initial()))
        self._results = self.DeclareAbstractInputPort("contact_results",
                                                      AbstractValue.Make(ContactResults()))
        # The compliant wall's own cells (its foundation realisation), when it has them.
        self._wall = (self.DeclareAbstractInputPort("wall_contact",
                                                    AbstractValue.Make(empty_wall_contact()))
                      if wall else None)
        self.DeclareStateOutputPort("map", self._state)
        if self.layout.pressure_field:
            # An unrestricted update: with the plant's own step (itself one, with sampled
            # output ports), it reads the state held up to t, as the loggers' publish at t
            # does, so the map samples what logs.npz samples.
            self.DeclarePeriodicUnrestrictedUpdateEvent(self.layout.period, 0.0,
                                                        self._sample)

    @property
    def grid(self) -> PatchGrid:
        return self.layout.grid

    def sampled(self, context) -> np.ndarray:
        """The state vector after a sample of the contact results at the context's time
        (what the periodic update stores; `layout` reads it). Only the patches pressed now
        or in a spell are updated: the capsule touches a few at a time."""
        x = np.array(context.get_discrete_state(self._state).get_value())
        peak, start, longest, counts = self.layout.split(x)   # views into x
        points, pressures, point_contacts = contact_faces(self._results.Eval(context))
        if self._wall is not None:
            cells = self._wall.Eval(context)
            if len(cells.pressures):
                points = np.concatenate([points, cells.points_W])
                pressures = np.concatenate([pressures, cells.pressures])
        t = context.get_time()
        pressed = (patch_index(*self._locator.locate(points), self.grid) if len(points)
                   else np.zeros(0, dtype=np.int64))
        active = np.union1d(np.flatnonzero(~np.isnan(start).all(axis=0)), pressed)
        if active.size:
            sample = patch_peaks(np.searchsorted(active, pressed), pressures, active.size)
            peak[active], start[:, active], longest[:, active] = accumulate(
                peak[active], start[:, active], longest[:, active], sample, t, self._levels)
        counts[:] = [counts[0] + 1, counts[1] + (point_contacts > 0),
                     counts[2] if counts[0] > 0 else t, t]
        return x

    def _sample(self, context, state):
        state.get_mutable_discrete_state().get_mutable_vector(self._state).SetFromVector(
            self.sampled(context))
        return EventStatus.Succeeded()

    def wall_pressure(self, context) -> WallPressure:
        """The map in this system's `context` (its own, or the root's)."""
        try:
            self.ValidateContext(context)
        except RuntimeError:  # a root context
            context = self.GetMyContextFromRoot(context)
        return self.layout.map_of(context.get_discrete_state(self._state).get_value())
