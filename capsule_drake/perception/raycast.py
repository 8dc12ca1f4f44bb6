"""A second, independent image path for capsule frames: a ray caster over the colon's wall
mesh with a shading model of its own.

The simulator's camera renders with RenderEngineVtk (`capsule/camera.py`): one point light
at the lens, VTK's Phong shading, the procedural mucosa texture. A detector whose parameters
were chosen on those frames may have learned that look. This renderer shares only the
geometry (the wall mesh) and the lens model (`perception/lens.py`) with it; the rest is its
own:

- rays: every pixel's ray through the lens model, first hit on the wall mesh (Embree, through
  trimesh), normals interpolated from the mesh's vertex normals;
- light: a ring of `led_count` LEDs at radius `led_offset` around the lens, each emitting
  along the optical axis with the profile cos(alpha)^spot_exponent, the irradiance falling as
  1 / d^falloff_exponent (2 for a point source; a capsule's LEDs at a few millimetres from the
  tissue are not points);
- surface: Lambertian albedo from a 3D procedural texture (value noise for the colour's
  variation, ridged noise for vessels; not the mucosa texture the VTK path maps) plus a
  Blinn-Phong specular lobe (wet mucosa shines), plus an ambient term;
- sensor: an exposure that puts a wall 15 mm ahead at `exposure` of full scale, a gamma.

`Shading.sample(rng)` draws all of these at random, for scoring a detector under light it was
not tuned on. Depth is the range along each pixel's ray (m), +inf where no wall is within
`far`.
"""

import dataclasses

import numpy as np
import trimesh

from capsule_drake.perception.lens import Lens, LensConfig

try:  # Embree (the embreex package, a dependency): ~100x trimesh's own intersector.
    from trimesh.ray.ray_pyembree import RayMeshIntersector
except ImportError:  # pragma: no cover
    from trimesh.ray.ray_triangle import RayMeshIntersector


@dataclasses.dataclass
class Shading:
    """The ray caster's photometry (module docstring). Every field has a default."""

    # Irradiance falls as 1 / d^falloff_exponent (d in m).
    falloff_exponent: float = 2.0
    # Each LED's emission profile cos(alpha)^spot_exponent about the optical axis.
    spot_exponent: float = 1.0
    # LEDs on a ring of this radius (m) around the lens, in its plane.
    led_count: int = 4
    led_offset: float = 0.004
    # Ambient light, as a fraction of the wall's brightness 15 mm ahead.
    ambient: float = 0.0
    # Blinn-Phong specular lobe: strength relative to the diffuse albedo, and exponent.
    specular: float = 0.15
    shininess: float = 30.0
    # Base colour of the mucosa (linear RGB, 0-1), the strength of its variation, and the
    # vessels' colour, width and density (vessels per centimetre, roughly).
    albedo: tuple = (0.78, 0.36, 0.30)
    variation: float = 0.25
    vessel_rgb: tuple = (0.45, 0.08, 0.10)
    vessel_width: float = 0.06
    vessel_density: float = 1.0
    texture_seed: int = 0
    # The wall 15 mm straight ahead reads `exposure` of full scale (linear), then the image
    # is encoded with this gamma.
    exposure: float = 0.7
    gamma: float = 2.2

    @classmethod
    def sample(cls, rng, only: str | None = None) -> "Shading":
        """Random photometry over the ranges a capsule camera may meet: softer to steeper
        fall-off, flat to narrow spots, a point light to a wide LED ring, some ambient light
        (a second source, scatter), matte to wet, pale to dark mucosa, few to many vessels,
        under- to over-exposure. `only` (a key of SHADING_GROUPS) varies that group alone,
        the rest at its defaults."""
        base = np.array(cls.albedo) * rng.uniform(0.7, 1.2) * rng.uniform(0.85, 1.15, 3)
        drawn = dict(
            falloff_exponent=float(rng.uniform(1.5, 2.5)),
            spot_exponent=float(rng.uniform(0.0, 6.0)),
            led_count=int(rng.integers(1, 7)),
            led_offset=float(rng.uniform(0.0, 0.005)),
            ambient=float(rng.uniform(0.0, 0.05)),
            specular=float(rng.uniform(0.0, 0.6)),
            shininess=float(rng.uniform(5.0, 120.0)),
            albedo=tuple(np.clip(base, 0.05, 1.0).tolist()),
            variation=float(rng.uniform(0.05, 0.45)),
            vessel_rgb=tuple((np.array(cls.vessel_rgb) * rng.uniform(0.6, 1.4)).tolist()),
            vessel_width=float(rng.uniform(0.02, 0.12)),
            vessel_density=float(rng.uniform(0.3, 2.5)),
            texture_seed=int(rng.integers(0, 2**31 - 1)),
            exposure=float(rng.uniform(0.35, 1.3)),
            gamma=float(rng.uniform(1.8, 2.6)),
        )
        if only is not None:
            drawn = {key: drawn[key] for key in SHADING_GROUPS[only]}
        return cls(**drawn)


SHADING_GROUPS = {
    "falloff": ("falloff_exponent",),
    "spot": ("spot_exponent", "led_count", "led_offset"),
    "ambient": ("ambient",),
    "specular": ("specular", "shininess"),
    "texture": ("albedo", "variation", "vessel_rgb", "vessel_width", "vessel_density",
                "texture_seed"),
    "sensor": ("exposure", "gamma"),
}
"""The fields `Shading.sample(rng, only=...)` varies together."""


def _hash_lattice(ix, iy, iz, seed: int) -> np.ndarray:
    """A pseudo-random value in [0, 1) per integer lattice point (a 32-bit integer hash)."""
    h = (ix.astype(np.int64) * 73856093) ^ (iy.astype(np.int64) * 19349663) \
        ^ (iz.astype(np.int64) * 83492791) ^ (seed * 2654435761)
    h = h & 0xFFFFFFFF
    h = (h ^ (h >> 13)) * 1274126177 & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF) / float(1 << 24)


def value_noise(points, scale: float, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at `points` (N, 3), features of size ~`scale` (m)."""
    q = np.asarray(points, dtype=float) / scale
    base = np.floor(q)
    f = q - base
    f = f * f * (3.0 - 2.0 * f)
    i = base.astype(np.int64)
    total = np.zeros(len(q))
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1.0 - f[:, 0]
        for dy in (0, 1):
            wy = f[:, 1] if dy else 1.0 - f[:, 1]
            for dz in (0, 1):
                wz = f[:, 2] if dz else 1.0 - f[:, 2]
                total += wx * wy * wz * _hash_lattice(i[:, 0] + dx, i[:, 1] + dy,
                                                      i[:, 2] + dz, seed)
    return total


def mucosa_albedo(points_W, shading: Shading) -> np.ndarray:
    """(N, 3) linear albedo at wall points: the base colour varied by two octaves of value
    noise, with vessels where ridged noise is near its ridge."""
    seed = shading.texture_seed
    variation = 0.65 * value_noise(points_W, 0.008, seed) + 0.35 * value_noise(
        points_W, 0.002, seed + 1)
    colour = np.array(shading.albedo)[None, :] * (
        1.0 + shading.variation * (variation[:, None] - 0.5) * 2.0)
    scale = 0.01 / max(shading.vessel_density, 1e-3)
    ridge = np.abs(value_noise(points_W, scale, seed + 2) - 0.5)
    vessel = np.clip(1.0 - ridge / max(shading.vessel_width * 0.5, 1e-6), 0.0, 1.0) ** 2
    colour = colour * (1.0 - vessel[:, None]) + np.array(shading.vessel_rgb)[None, :] * vessel[
        :, None]
    return np.clip(colour, 0.0, 1.0)


class RayCaster:
    """Renders a wall mesh through a lens model with `Shading` (module docstring).

    Args:
        mesh: the wall (trimesh.Trimesh), in world coordinates (m).
        lens: LensConfig of the camera.
        far: largest range (m); farther walls are black and their depth +inf.
    """

    def __init__(self, mesh: trimesh.Trimesh, lens: LensConfig | None = None,
                 far: float = 0.2):
        self.mesh = mesh
        self.lens = Lens(lens or LensConfig())
        rays, field = self.lens.pixel_rays()
        self._rays_C = rays.reshape(-1, 3)
        self.field = field
        self.far = float(far)
        self._normals = np.asarray(mesh.vertex_normals)
        self._intersector = RayMeshIntersector(mesh)

    def cast(self, X_WC):
        """First hits of every in-field pixel ray from camera pose X_WC (RigidTransform):
        a `Hits` with the pixel indices, points and normals in the camera frame."""
        R = X_WC.rotation().matrix()
        p = X_WC.translation()
        inside = np.flatnonzero(self.field.ravel())
        directions = self._rays_C[inside] @ R.T
        origins = np.repeat(p[None, :], len(inside), axis=0)
        tri, ray, points = self._intersector.intersects_id(
            origins, directions, multiple_hits=False, return_locations=True)
        distance = np.einsum("ij,ij->i", points - p[None, :], directions[ray])
        keep = (distance > 0.0) & (distance <= self.far)
        tri, ray, points, distance = tri[keep], ray[keep], points[keep], distance[keep]
        faces = self.mesh.faces[tri]
        barycentric = trimesh.triangles.points_to_barycentric(
            self.mesh.vertices[faces], points)
        normals = np.einsum("ij,ijk->ik", barycentric, self._normals[faces])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        return Hits(inside[ray], (points - p[None, :]) @ R, normals @ R, points, distance)

    def shade(self, hits, shading: Shading) -> np.ndarray:
        """(H, W, 3) uint8 RGB of cast `hits` under `shading`."""
        H, W = self.field.shape
        image = np.zeros((H * W, 3))
        p = hits.points_C
        n = hits.normals_C
        view = -p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)
        n = n * np.where(np.einsum("ij,ij->i", n, view) < 0.0, -1.0, 1.0)[:, None]
        diffuse = np.zeros(len(p))
        specular = np.zeros(len(p))
        count = max(int(shading.led_count), 1)
        for k in range(count):
            angle = 2.0 * np.pi * k / count
            q = np.array([np.cos(angle), np.sin(angle), 0.0]) * shading.led_offset
            to_light = q[None, :] - p
            d = np.maximum(np.linalg.norm(to_light, axis=1), 1e-4)
            light = to_light / d[:, None]
            emit = np.clip(-light[:, 2], 0.0, 1.0) ** shading.spot_exponent
            irradiance = emit / d ** shading.falloff_exponent / count
            cos_in = np.clip(np.einsum("ij,ij->i", n, light), 0.0, 1.0)
            diffuse += irradiance * cos_in
            half = light + view
            half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
            specular += irradiance * cos_in * np.clip(
                np.einsum("ij,ij->i", n, half), 0.0, 1.0) ** shading.shininess
        reference = 1.0 / 0.015 ** shading.falloff_exponent
        albedo = mucosa_albedo(hits.points_W, shading)
        radiance = (albedo * (diffuse / reference + shading.ambient)[:, None]
                    + shading.specular * (specular / reference)[:, None])
        image[hits.pixels] = radiance * shading.exposure
        encoded = np.clip(image, 0.0, 1.0) ** (1.0 / shading.gamma)
        return np.round(255.0 * encoded).astype(np.uint8).reshape(H, W, 3)

    def range_image(self, hits) -> np.ndarray:
        """(H, W) float32 range along each pixel's ray (m), +inf where nothing was hit."""
        H, W = self.field.shape
        depth = np.full(H * W, np.inf, dtype=np.float32)
        depth[hits.pixels] = hits.distance
        return depth.reshape(H, W)

    def render(self, X_WC, shading: Shading | None = None):
        """RGB (H, W, 3) uint8 and range (H, W) float32 from camera pose X_WC."""
        hits = self.cast(X_WC)
        return self.shade(hits, shading or Shading()), self.range_image(hits)


@dataclasses.dataclass
class Hits:
    """What `RayCaster.cast` found: per hit, its pixel's flat index, the point in the camera
    and world frames, the unit normal in the camera frame and the range."""

    pixels: np.ndarray
    points_C: np.ndarray
    normals_C: np.ndarray
    points_W: np.ndarray
    distance: np.ndarray
