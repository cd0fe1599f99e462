from .base import AbstractMethod as AbstractMethod, RootFindStats as RootFindStats
from .discrete_gradient import (
    averaged_structure as averaged_structure,
    DiscreteGradient as DiscreteGradient,
    midpoint_structure as midpoint_structure,
)
