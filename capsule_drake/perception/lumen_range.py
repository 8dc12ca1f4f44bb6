"""LumenRange: how far the lumen the tracker sees stays open, read from the depth image.

The camera's depth image holds range along each pixel's ray (systems/camera.py), so the
depth at the detected lumen's pixel is the free distance along the lumen ray: how far the
capsule could travel toward the lumen before it meets tissue. An operator judges this from
the shading (the light falls off with distance, sources.md s. 5); shared control uses
it to keep the EPM's lead inside the lumen it can see (teleop/mapping.py, `assist`).
"""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F


def free_range(depth, pixel, far: float, patch: int = 2) -> float:
    """Median range (m) over a (2 patch + 1)^2 window of `depth` around `pixel` ([u, v]).

    Pixels beyond the far clip (+inf) count as `far`; pixels nearer than the near clip
    (0) count as 0. NaN when the pixel is not finite or lies outside the image.
    """
    pixel = np.asarray(pixel, dtype=float)
    if not np.all(np.isfinite(pixel)):
        return float("nan")
    height, width = depth.shape[:2]
    u, v = int(round(pixel[0])), int(round(pixel[1]))
    if not (0 <= u < width and 0 <= v < height):
        return float("nan")
    window = depth[max(0, v - patch):v + patch + 1, max(0, u - patch):u + patch + 1]
    window = np.where(np.isfinite(window), window, far)
    return float(np.median(window))


class LumenRange(LeafSystem):
    """Free range along the detected lumen ray (module docstring).

    .. pydrake_system::

        name: LumenRange
        input_ports:
        - depth_image
        - lumen_pixel
        - lumen_visible
        output_ports:
        - range

    range: metres, NaN while the lumen is not visible.

    Args:
        far: the camera's far clip (m): what +inf depth stands for.
    """

    def __init__(self, far: float):
        super().__init__()
        self._far = float(far)
        self._depth = self.DeclareAbstractInputPort(
            "depth_image", AbstractValue.Make(ImageDepth32F(1, 1)))
        self._pixel = self.DeclareVectorInputPort("lumen_pixel", 2)
        self._visible = self.DeclareVectorInputPort("lumen_visible", 1)
        self.DeclareVectorOutputPort("range", 1, self._calc)

    def _calc(self, context, output):
        if float(self._visible.Eval(context)[0]) <= 0.5:
            output.SetAtIndex(0, float("nan"))
            return
        depth = self._depth.Eval(context).data[..., 0]
        output.SetAtIndex(0, free_range(depth, self._pixel.Eval(context), self._far))
