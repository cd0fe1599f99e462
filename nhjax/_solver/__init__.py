from .base import AbstractMethod as AbstractMethod, MethodState as MethodState
from .discrete_gradient import (
    averaged_structure as averaged_structure,
    DiscreteGradient as DiscreteGradient,
    midpoint_structure as midpoint_structure,
)
from .gonzalez_r import GonzalezR as GonzalezR
from .gonzalez_f import GonzalezF as GonzalezF
