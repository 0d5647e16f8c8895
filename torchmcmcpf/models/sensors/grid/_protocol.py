"""What the evaluation paths read of a grid sensor: :class:`GridSensorLike`.

The paths (:mod:`.whole`, :mod:`.window`, :mod:`.delta`, :mod:`.slots`, :mod:`.amplitudes`,
:mod:`.data`, :mod:`.inputs`) take the sensor as their first argument but import only this
protocol, and :class:`~.sensor.SeparableGridSensor`, which satisfies it, imports them: the
package's imports run one way (``sensor`` on top, the paths below it, this module, ``geometry``,
``spread`` and ``chunks`` at the bottom).
"""

from __future__ import annotations

from typing import Protocol

from ....typing import Tensor
from .geometry import GridGeometry

__all__ = ["GridSensorLike"]


class GridSensorLike(Protocol):
    """The attributes and hooks of :class:`~.sensor.SeparableGridSensor` that the
    evaluation paths use (see there for their meaning).
    """

    @property
    def dim(self) -> int: ...

    @property
    def n_axes(self) -> int: ...

    @property
    def frame_shape(self) -> tuple[int, ...]: ...

    @property
    def geometry(self) -> GridGeometry: ...

    @property
    def box_offsets(self) -> Tensor: ...

    @property
    def method(self) -> str: ...

    @property
    def memory_budget(self) -> int: ...

    @property
    def max_neighbours(self) -> int: ...

    @property
    def detection_threshold(self) -> float: ...

    @property
    def max_peaks(self) -> int: ...

    @property
    def peak_spread(self) -> float: ...

    @property
    def uniform_weight(self) -> float: ...

    def all_bins(self) -> tuple[Tensor, ...]: ...

    def measurement_coords(self, x: Tensor) -> Tensor: ...

    def signal(self, x: Tensor) -> Tensor: ...

    def prepare_frame(self, z: Tensor) -> Tensor: ...

    def cell_log_ratio(self, A: Tensor, zc: Tensor) -> Tensor: ...
    def native_ratio(self) -> tuple[str, float] | None: ...

    def detection_statistic(self, z: Tensor) -> Tensor: ...

    def detection_signal(self, stat: Tensor) -> Tensor: ...

    def detection_stat(self, signal: Tensor) -> Tensor: ...
