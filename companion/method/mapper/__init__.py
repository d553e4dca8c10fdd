"""Monocular terrain mapper (seed 000, section II): features -> EKF -> converged terrain points.

See docs/mapper.md for the equations as implemented.
"""

from companion.method.mapper.depth_prior import DepthPrior, flat_ground_ranges
from companion.method.mapper.mapper import FeatureSnapshot, Mapper, MapperStep, mean_innovation_squared

__all__ = ["DepthPrior", "FeatureSnapshot", "Mapper", "MapperStep", "flat_ground_ranges", "mean_innovation_squared"]
