"""Lens models of capsule cameras: rays in the camera frame <-> pixels. Pure numpy.

Camera frame C (Drake's and OpenCV's convention): +z forward along the optical axis,
+x right and +y down in the image. Pixel coordinates follow OpenCV: (u, v) = (column, row),
the centre of the top-left pixel is (0, 0), so a W x H image spans [-0.5, W - 0.5] x
[-0.5, H - 0.5] and its centre is ((W - 1) / 2, (H - 1) / 2).

Models (theta = angle between the ray and +z, phi = the ray's azimuth about +z):

    equidistant      r = f theta                                       (ideal fisheye)
    kannala_brandt   r = f theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
                     (OpenCV's `cv2.fisheye` model; here theta may exceed 90 degrees)
    pinhole_radtan   x = X / Z, y = Y / Z, r^2 = x^2 + y^2,
                     x' = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
                     y' = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
                     (OpenCV's `cv2.projectPoints` with distortion (k1, k2, p1, p2, k3))

and u = fx x' + cx, v = fy y' + cy (fisheye: x' = r cos(phi) / f, y' = r sin(phi) / f).

Unless fx, fy, cx, cy are given, a fisheye's focal length puts the field of view's edge
(theta = fov / 2) on the circle inscribed in the image (radius min(W, H) / 2 px), and a
pinhole's makes `fov_deg` the undistorted field across the image width.
"""

import dataclasses
import math

import numpy as np

MODELS = ("equidistant", "kannala_brandt", "pinhole_radtan")
FISHEYE_MODELS = ("equidistant", "kannala_brandt")
DEFAULT_FISHEYE_FOV_DEG = 172.0  # PillCam COLON 2 (docs/sources.md section 2)
DEFAULT_PINHOLE_FOV_DEG = 120.0

_NEWTON_TOLERANCE = 1e-12  # rad (fisheye) or normalised image units (pinhole)
_NEWTON_MAX_ITERATIONS = 50


@dataclasses.dataclass
class LensConfig:
    """A capsule camera's lens and sensor. YAML-loadable; every field has a default."""

    # Projection model: "equidistant", "kannala_brandt" or "pinhole_radtan" (module docstring).
    model: str = "equidistant"
    # Image size (px).
    width: int = 256
    height: int = 256
    # Full field of view (deg). Fisheye: the diameter of the image circle, inscribed in the
    # shorter image side (PillCam COLON 2: 172). Pinhole: across the image width, without
    # distortion. None: 172 for the fisheye models, 120 for the pinhole.
    fov_deg: float | None = None
    # Kannala-Brandt coefficients k1..k4 (dimensionless, per rad^2 .. rad^8), OpenCV's order.
    kb_coefficients: list[float] = dataclasses.field(
        default_factory=lambda: [0.0, 0.0, 0.0, 0.0])
    # Radial-tangential coefficients in OpenCV's order k1, k2, p1, p2, k3 (dimensionless).
    radtan_coefficients: list[float] = dataclasses.field(
        default_factory=lambda: [0.0, 0.0, 0.0, 0.0, 0.0])
    # Explicit intrinsics (px); None derives them from the field of view and the image size.
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None


class Lens:
    """Projection and unprojection through one `LensConfig`.

    Attributes (read-only after construction): config, width, height, fx, fy, cx, cy,
    max_theta (rad: the half field of view; rays beyond it are outside the lens's field).
    """

    def __init__(self, config: LensConfig | None = None):
        config = dataclasses.replace(config) if config is not None else LensConfig()
        if config.model not in MODELS:
            raise ValueError(f"lens model {config.model!r} is not one of {MODELS}")
        if config.width < 1 or config.height < 1:
            raise ValueError(f"lens image size {config.width} x {config.height} px")
        self.config = config
        self.model = config.model
        self.is_fisheye = config.model in FISHEYE_MODELS
        self.width, self.height = int(config.width), int(config.height)
        fov_deg = config.fov_deg
        if fov_deg is None:
            fov_deg = DEFAULT_FISHEYE_FOV_DEG if self.is_fisheye else DEFAULT_PINHOLE_FOV_DEG
        limit = 360.0 if self.is_fisheye else 180.0
        if not 0.0 < fov_deg < limit:
            raise ValueError(f"lens fov_deg {fov_deg} must be in (0, {limit}) for {self.model}")
        self.fov_deg = float(fov_deg)
        self.max_theta = math.radians(fov_deg) / 2.0
        if self.model == "equidistant":
            self._kb = np.zeros(4)
        else:
            self._kb = np.asarray(config.kb_coefficients, dtype=float)
            if self._kb.shape != (4,):
                raise ValueError("lens kb_coefficients must be 4 numbers k1..k4")
        self._radtan = np.asarray(config.radtan_coefficients, dtype=float)
        if self._radtan.shape != (5,):
            raise ValueError("lens radtan_coefficients must be 5 numbers k1, k2, p1, p2, k3")
        if self.is_fisheye:
            # The radial polynomial must increase over the field, or two rays share a pixel.
            self._theta_limit = self._monotonic_limit(
                self._fisheye_radius_derivative, math.pi)
            if self._theta_limit <= self.max_theta:
                raise ValueError(
                    f"lens kb_coefficients fold the image before theta = {fov_deg / 2} deg")
            default_f = (min(self.width, self.height) / 2.0) / self._fisheye_radius(
                self.max_theta)
        else:
            self._theta_limit = math.pi / 2.0
            default_f = (self.width / 2.0) / math.tan(self.max_theta)
            # Undistorted radius beyond which the radial distortion folds back.
            self._r_limit = self._monotonic_limit(self._radtan_radial_derivative, 50.0)
        self.fx = float(config.fx) if config.fx is not None else default_f
        self.fy = float(config.fy) if config.fy is not None else default_f
        self.cx = float(config.cx) if config.cx is not None else (self.width - 1) / 2.0
        self.cy = float(config.cy) if config.cy is not None else (self.height - 1) / 2.0

    # ---- radial functions ------------------------------------------------------------------
    def _fisheye_radius(self, theta):
        """Distorted normalised radius d(theta) = theta (1 + k1 theta^2 + ... + k4 theta^8)."""
        t2 = np.square(theta)
        k1, k2, k3, k4 = self._kb
        return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def _fisheye_radius_derivative(self, theta):
        t2 = np.square(theta)
        k1, k2, k3, k4 = self._kb
        return 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))

    def _radtan_radial_derivative(self, r):
        """d/dr of r (1 + k1 r^2 + k2 r^4 + k3 r^6)."""
        k1, k2, _, _, k3 = self._radtan
        r2 = np.square(r)
        return 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))

    @staticmethod
    def _monotonic_limit(derivative, upper: float) -> float:
        """The first argument in (0, upper] where `derivative` stops being positive."""
        grid = np.linspace(0.0, upper, 200001)
        bad = np.nonzero(derivative(grid) <= 0.0)[0]
        return float(grid[bad[0]]) if len(bad) else float(upper)

    # ---- projection -----------------------------------------------------------------------
    def project(self, rays_C) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of rays (or points) given in the camera frame.

        Args:
            rays_C: (N, 3) directions or points in C; need not be unit length.

        Returns:
            (pixels (N, 2) as (u, v), valid (N,) bool). valid: the ray is inside the lens's
            field of view (theta <= fov / 2) and its pixel inside the image. Pixels of invalid
            rays are still computed where the model defines them (NaN where it does not).
        """
        rays = np.atleast_2d(np.asarray(rays_C, dtype=float))
        x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
        rho = np.hypot(x, y)
        norm = np.hypot(rho, z)
        if self.is_fisheye:
            theta = np.arctan2(rho, z)
            d = self._fisheye_radius(theta)
            safe_rho = np.where(rho > 0.0, rho, 1.0)
            xd = np.where(rho > 0.0, d * x / safe_rho, 0.0)
            yd = np.where(rho > 0.0, d * y / safe_rho, 0.0)
            in_field = (theta <= self.max_theta + 1e-12) & (norm > 0.0)
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                xn = np.where(z > 0.0, x / z, np.nan)
                yn = np.where(z > 0.0, y / z, np.nan)
            xd, yd = self._distort(xn, yn)
            # Rays within the field across the width (or the image bounds, checked below) and
            # inside the radius where the distortion is still one-to-one.
            in_field = (z > 0.0) & (np.hypot(xn, yn) < self._r_limit)
        pixels = np.column_stack([self.fx * xd + self.cx, self.fy * yd + self.cy])
        with np.errstate(invalid="ignore"):
            inside = ((pixels[:, 0] >= -0.5) & (pixels[:, 0] <= self.width - 0.5)
                      & (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= self.height - 0.5))
        return pixels, in_field & inside

    def _distort(self, x, y):
        k1, k2, p1, p2, k3 = self._radtan
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return xd, yd

    # ---- unprojection ---------------------------------------------------------------------
    def unproject(self, pixels) -> np.ndarray:
        """Unit rays in the camera frame through pixels (u, v).

        Inverts the model by Newton iteration (fisheye: on the radial polynomial in theta;
        pinhole: on the 2-D radial-tangential map), converged to 1e-12. Pixels outside the
        image circle still get their (extrapolated) ray while the model is one-to-one there;
        `in_field` tells which rays the lens really sees.

        Args:
            pixels: (N, 2) pixel coordinates (u, v).

        Returns:
            (N, 3) unit rays.
        """
        pixels = np.atleast_2d(np.asarray(pixels, dtype=float))
        xd = (pixels[:, 0] - self.cx) / self.fx
        yd = (pixels[:, 1] - self.cy) / self.fy
        if self.is_fisheye:
            d = np.hypot(xd, yd)
            theta = self._solve_theta(d)
            safe_d = np.where(d > 0.0, d, 1.0)
            s = np.sin(theta)
            rays = np.column_stack([np.where(d > 0.0, s * xd / safe_d, 0.0),
                                    np.where(d > 0.0, s * yd / safe_d, 0.0),
                                    np.cos(theta)])
        else:
            x, y = self._undistort(xd, yd)
            rays = np.column_stack([x, y, np.ones_like(x)])
            rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return rays

    def _solve_theta(self, d):
        """theta with d(theta) = d, by safeguarded Newton iteration in [0, theta_limit]."""
        if not np.any(self._kb):
            return np.minimum(d, self._theta_limit)
        hi = np.full_like(d, self._theta_limit)
        beyond = d >= self._fisheye_radius(self._theta_limit)
        lo = np.zeros_like(d)
        theta = np.clip(d, 0.0, self._theta_limit)
        for _ in range(_NEWTON_MAX_ITERATIONS):
            f = self._fisheye_radius(theta) - d
            # Keep a bracket so a poor start never leaves the monotonic range.
            lo = np.where(f < 0.0, theta, lo)
            hi = np.where(f > 0.0, theta, hi)
            step = f / self._fisheye_radius_derivative(theta)
            candidate = theta - step
            outside = (candidate <= lo) | (candidate >= hi)
            candidate = np.where(outside, 0.5 * (lo + hi), candidate)
            change = np.abs(candidate - theta)
            theta = candidate
            if np.all((change < _NEWTON_TOLERANCE) | beyond):
                break
        else:
            raise RuntimeError("lens: Newton iteration on theta did not converge")
        return np.where(beyond, self._theta_limit, theta)

    def _undistort(self, xd, yd):
        """(x, y) with distort(x, y) = (xd, yd), by 2-D Newton iteration."""
        if not np.any(self._radtan):
            return xd.copy(), yd.copy()
        k1, k2, p1, p2, k3 = self._radtan
        x, y = xd.copy(), yd.copy()
        for _ in range(_NEWTON_MAX_ITERATIONS):
            fx_, fy_ = self._distort(x, y)
            ex, ey = fx_ - xd, fy_ - yd
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (2.0 * k2 + r2 * 3.0 * k3)  # d radial / d r2
            a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x  # dxd/dx
            b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y  # dxd/dy = dyd/dx
            c = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x  # dyd/dy
            det = a * c - b * b
            dx = (c * ex - b * ey) / det
            dy = (a * ey - b * ex) / det
            x -= dx
            y -= dy
            if np.all(np.hypot(dx, dy) < _NEWTON_TOLERANCE):
                break
        else:
            raise RuntimeError("lens: Newton iteration on the distortion did not converge")
        return x, y

    # ---- whole-image helpers --------------------------------------------------------------
    def pixel_grid(self) -> np.ndarray:
        """(H * W, 2) centres (u, v) of every pixel, row-major."""
        v, u = np.mgrid[0:self.height, 0:self.width]
        return np.column_stack([u.ravel(), v.ravel()]).astype(float)

    def in_field(self, rays_C) -> np.ndarray:
        """(N,) bool: the rays lie within the lens's field of view."""
        rays = np.atleast_2d(np.asarray(rays_C, dtype=float))
        theta = np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2])
        if self.is_fisheye:
            return theta <= self.max_theta + 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            return (rays[:, 2] > 0.0) & (np.tan(theta) < self._r_limit)

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit rays of every pixel, (H, W, 3), and the (H, W) mask of those in the field."""
        rays = self.unproject(self.pixel_grid())
        return (rays.reshape(self.height, self.width, 3),
                self.in_field(rays).reshape(self.height, self.width))

    def solid_angles(self) -> np.ndarray:
        """(H, W): the solid angle (sr) each pixel sees, 0 outside the field: the area of
        the parallelogram spanned by the unit ray's change across the pixel's width and
        height (central differences over the pixel, where the map is smooth). A pinhole's
        pixels see less toward the image's edge (cos^3 of the angle off the axis, before
        distortion); an equidistant fisheye's about sin(theta) / theta as much. Computed
        once per lens."""
        if getattr(self, "_solid_angles", None) is None:
            H, W = self.height, self.width
            grid = self.pixel_grid()

            def rays(du, dv):
                r = self.unproject(grid + np.array([du, dv]))
                return (r / np.linalg.norm(r, axis=1, keepdims=True)).reshape(H, W, 3)

            across = rays(0.5, 0.0) - rays(-0.5, 0.0)
            down = rays(0.0, 0.5) - rays(0.0, -0.5)
            omega = np.linalg.norm(np.cross(across, down), axis=2)
            field = self.pixel_rays()[1]
            self._solid_angles = np.where(field, np.nan_to_num(omega), 0.0)
            self._solid_angles.setflags(write=False)
        return self._solid_angles

    def inside_angles(self) -> np.ndarray:
        """(H, W): how far each pixel's ray lies inside the field's edge (degrees: the least
        angle to the ray of a pixel on the field's border, the image's edge included), 0
        outside the field. An equidistant fisheye's is its angle from the image circle; a
        pinhole's shrinks toward the image's edge faster than its pixels do. Computed once
        per lens."""
        if getattr(self, "_inside_angles", None) is None:
            rays, field = self.pixel_rays()
            padded = np.pad(field, 1, constant_values=False)
            interior = (padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2]
                        & padded[1:-1, 2:] & field)
            border = rays[field & ~interior]
            border = border / np.linalg.norm(border, axis=1, keepdims=True)
            unit = rays.reshape(-1, 3) / np.linalg.norm(rays.reshape(-1, 3), axis=1,
                                                         keepdims=True)
            nearest = np.full(len(unit), -1.0)
            for start in range(0, len(unit), 4096):
                nearest[start:start + 4096] = (unit[start:start + 4096] @ border.T).max(axis=1)
            angle = np.degrees(np.arccos(np.clip(nearest, -1.0, 1.0))).reshape(field.shape)
            self._inside_angles = np.where(field, angle, 0.0)
            self._inside_angles.setflags(write=False)
        return self._inside_angles
