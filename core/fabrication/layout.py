"""From the halftone grid to the machine: rotation, shift and scale (thesis 5.2, eq. 5.2-5.3).

Frames.
- Image frame (cells): ``X`` along columns, ``Y`` along rows (down); cell ``(x, y)``
  covers ``[x, x+1] x [y, y+1]``.
- Print frame (cells): ``P = (X, rows - Y)``, right-handed with the image's top up, so
  the sheet, seen from above, shows the image unmirrored.
- Machine frame (mm): ``M = s R(theta) P + offset``, X right, Y away from the operator.

Centrelines. Discrete line ``k`` (see :mod:`.halftone`) is scratched along the straight
line ``Y(X) = k + 1/2 + a (X - 1/2) / b - (b - g) / (2 b)``, ``g = gcd(a, b)``, which
passes through every one of its pixels (at the pixel's centre column it lies
``(2 r + g) / (2 b)`` below the pixel's top edge, ``r = a x mod b``), so adjacent lines
are ``b / sqrt(a^2 + b^2)`` cells apart measured perpendicular to them.

Rotation (eq. 5.2-5.3). The lines are turned onto the machine's y axis, the blade's
cutting direction: in the print frame they point along ``(b, -a)``, at
``-arctan(a / b)`` to the x axis (eq. 5.2's ``arccos(<[0 1], ls/|ls|>)`` with
``ls = [a b]`` is the same angle ``arctan(a / b)``, measured in the thesis's
row/column array frame), so ``theta = arctan(a / b) - 90 deg`` maps them onto -y.

Scale (departure from the thesis, tested). Thesis 5.2 multiplies the rotated
coordinates "with the scratch thickness" so that "the distance between two lines
equals the scratch thickness". For a slope a/b that is not 0 this does not hold: lines
one cell apart vertically are only ``b / sqrt(a^2 + b^2)`` (0.868 for 4/7) apart
perpendicularly, so scratches 90 um wide would overlap by 13 % and a full-coverage print
would be scratched over more than its area. Here the cell is scaled to
``s = thickness * sqrt(a^2 + b^2) / b`` (0.1037 mm), which makes adjacent lines exactly one
scratch thickness apart; then every halftone pixel accounts for exactly one cell of
scratched area (along-line length ``sqrt(a^2+b^2)/b`` cells times one pitch of width) and
the area fraction of the sheet covered by scratches equals the halftone's coverage.

Shift. The thesis subtracts each axis' minimum over the lines so the print sits "as
close as possible to the zero position". Here the minimum is taken over the corners of
the rotated print (so the print lands at the same place whatever its content) and the
print is moved to ``print_origin_mm`` of the machine description, plus less than one
machine step so that every line's x lies exactly on the machine's 10 um grid.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.fabrication.machine import Machine, ScreenParams


def cell_size_mm(thickness_mm: float, screen: ScreenParams) -> float:
    """Side of one halftone cell such that adjacent discrete lines are one scratch thickness apart."""
    return thickness_mm * math.hypot(screen.a, screen.b) / screen.b


def rotation_angle(screen: ScreenParams) -> float:
    """Rotation (radians) that turns the discrete lines onto the machine's y axis (eq. 5.2)."""
    return math.atan2(screen.a, screen.b) - math.pi / 2


@dataclass(frozen=True)
class Layout:
    """Placement of a halftone grid of ``rows x cols`` cells on the machine bed."""

    a: int
    b: int
    rows: int
    cols: int
    cell_mm: float
    theta_rad: float
    offset_mm: tuple[float, float]

    @property
    def size_mm(self) -> tuple[float, float]:
        """Print width and height, in its own (unrotated) frame."""
        return self.cols * self.cell_mm, self.rows * self.cell_mm

    @property
    def pitch_cells(self) -> float:
        """Perpendicular distance between adjacent discrete lines, in cells."""
        return self.b / math.hypot(self.a, self.b)

    def _rot(self) -> np.ndarray:
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return np.array([[c, -s], [s, c]])

    def image_to_machine(self, X, Y) -> tuple[np.ndarray, np.ndarray]:
        """Image-frame cell coordinates -> machine mm (eq. 5.3, then shift and scale)."""
        P = np.stack([np.asarray(X, dtype=float), self.rows - np.asarray(Y, dtype=float)])
        M = self.cell_mm * np.tensordot(self._rot(), P, axes=1)
        return M[0] + self.offset_mm[0], M[1] + self.offset_mm[1]

    def machine_to_image(self, mx, my) -> tuple[np.ndarray, np.ndarray]:
        """Machine mm -> image-frame cell coordinates (inverse of :meth:`image_to_machine`)."""
        M = np.stack([np.asarray(mx, dtype=float) - self.offset_mm[0],
                      np.asarray(my, dtype=float) - self.offset_mm[1]]) / self.cell_mm
        P = np.tensordot(self._rot().T, M, axes=1)
        return P[0], self.rows - P[1]

    def corners_mm(self) -> np.ndarray:
        """The print's four corners in machine mm, ``(4, 2)``."""
        X = np.array([0.0, self.cols, self.cols, 0.0])
        Y = np.array([0.0, 0.0, self.rows, self.rows])
        return np.stack(self.image_to_machine(X, Y), axis=1)

    def bbox_mm(self) -> tuple[float, float, float, float]:
        """Bounding box ``(xmin, ymin, xmax, ymax)`` of the rotated print on the bed."""
        c = self.corners_mm()
        return (float(c[:, 0].min()), float(c[:, 1].min()), float(c[:, 0].max()), float(c[:, 1].max()))

    def centreline_y(self, k, X) -> np.ndarray:
        """Image-frame Y of the centreline of discrete line ``k`` at ``X`` (module docstring)."""
        g = math.gcd(self.a, self.b)
        return (np.asarray(k, dtype=float) + 0.5 + self.a * (np.asarray(X, dtype=float) - 0.5) / self.b
                - (self.b - g) / (2.0 * self.b))

    def to_json(self) -> dict:
        d = asdict(self)
        d["theta_deg"] = math.degrees(self.theta_rad)
        d["offset_mm"] = list(self.offset_mm)
        d["frames"] = ("image: X along columns, Y along rows (down), cells; machine = cell_mm * "
                       "R(theta) (X, rows - Y) + offset_mm")
        return d

    @classmethod
    def from_json(cls, d: dict, path=None) -> Layout:
        try:
            return cls(a=int(d["a"]), b=int(d["b"]), rows=int(d["rows"]), cols=int(d["cols"]),
                       cell_mm=float(d["cell_mm"]), theta_rad=float(d["theta_rad"]),
                       offset_mm=(float(d["offset_mm"][0]), float(d["offset_mm"][1])))
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise InputError(f"layout is incomplete or malformed: {e!r}", path=path) from None


def make_layout(rows: int, cols: int, machine: Machine) -> Layout:
    """Rotate, shift and scale a ``rows x cols`` halftone grid onto ``machine`` (module docstring)."""
    screen = machine.screen
    base = Layout(screen.a, screen.b, rows, cols, cell_size_mm(machine.scratch_thickness_mm, screen),
                  rotation_angle(screen), (0.0, 0.0))
    xmin, ymin, _, _ = base.bbox_mm()
    res = machine.resolution_mm
    ox, oy = (float(v) for v in machine.quantise(machine.print_origin_mm))
    # x of discrete line 0 once the bbox corner sits at the origin; nudge by < 1 step onto the grid
    x_line0, _ = base.image_to_machine(0.0, base.centreline_y(0, 0.0))
    x0 = float(x_line0) - xmin + ox
    nudge = (math.ceil(x0 / res - 1e-9) * res - x0) % res
    return Layout(screen.a, screen.b, rows, cols, base.cell_mm, base.theta_rad,
                  (ox - xmin + nudge, oy - ymin))
