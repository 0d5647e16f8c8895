"""Track-before-detect sensors on a separable cell grid: the shared machinery, by concern.

A TBD sensor of this family sees one value per cell of a regular grid ``*G = (N_1, ..., N_n)``
(range x doppler x bearing, azimuth x range, pixels). Target ``j`` maps to measurement
coordinates ``u_j`` (one per axis) and a signal ``s_j`` (amplitude or power), and spreads it
over the cells with a separable Gaussian point spread

    ``h(cell) = prod_a exp(-(c_a - u_{j,a})^2 / (2 w_a^2))``      (Bocquel et al. 2012, eq. 20)

so the signal in a cell is ``A(cell) = sum_j e_j s_j h_j(cell)`` (``e_j`` the existence flag).
Cells are independent given ``A``; a subclass gives the per-cell log-likelihood ratio
``cell_log_ratio(A, z)`` against "no target" (zero where ``A = 0``), and the sensor's
log-likelihood is its sum over cells.

:class:`SeparableGridSensor` (:mod:`.sensor`) is the one public face; each concern is a
module of its own:

- :mod:`.geometry`: the grid's cells and the boxes of the windowed paths (box placement,
  overlaps, cell gathers, which box counts each cell of the union);
- :mod:`.spread`: per-axis profiles and their sums over targets, over the whole grid or at
  the cells of a box with its neighbour slots;
- :mod:`.whole`: the reference, every cell of the grid, ``A`` by a contraction of per-axis
  profiles;
- :mod:`.window`: the fast path, each target's point spread truncated to a box of
  ``2 * window + 1`` cells per axis around its nearest cell, the exact log-likelihood of
  that truncated-spread sensor (a sum over the union of the boxes, a cell inside several
  boxes counted once). The truncation is the only approximation (spread values below
  ``exp(-(window + 1/2)^2 / 2)`` of the peak are dropped); with ``window`` at least the grid
  size the two paths agree to round-off. A box sums only the targets whose boxes overlap it
  (neighbour slots, :attr:`SeparableGridSensor.max_neighbours`), so the cost is
  ``O(N K W^n)``, not ``O(N K^2 W^n)``;
- :mod:`.delta`: the change of the windowed log-likelihood when one slot moves, from the
  cells of its old and new box only (the per-target refinement of the MCMC filter, the
  exchange move of the IP-MCMC-PF);
- :mod:`.slots`: every slot of one reference moved on its own (the independent-partition
  filter's weights);
- :mod:`.amplitudes`: the chain cache, each chain's amplitude per cell, and the change a
  move makes to it;
- :mod:`.chunks`: blocks of samples sized from ``memory_budget`` (autograd-checkpointed per
  block, so gradients stay within it too);
- :mod:`.data`: the data-driven proposal (the frame's peaks, the density around them);
- :mod:`.inputs`: the shape checks and the flattening every path shares.

Subclasses declare their constructor (their axes' bins and widths by name, their noise
parameter), pass the axes to the base, and implement :meth:`~SeparableGridSensor.measurement_coords`,
:meth:`~SeparableGridSensor.signal`, :meth:`~SeparableGridSensor.cell_log_ratio` (optionally
:meth:`~SeparableGridSensor.prepare_frame`) and ``simulate``.
"""

from .geometry import GridGeometry, lattice, materialise, polar
from .sensor import SeparableGridSensor

__all__ = ["SeparableGridSensor", "GridGeometry", "polar", "lattice", "materialise"]
