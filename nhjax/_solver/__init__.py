from .base import AbstractMethod as AbstractMethod, MethodState as MethodState
from .composition import (
    Composition as Composition,
    COMPOSITION_SCHEMES as COMPOSITION_SCHEMES,
    CompositionState as CompositionState,
)
from .discrete_gradient import (
    averaged_structure as averaged_structure,
    DiscreteGradient as DiscreteGradient,
    midpoint_structure as midpoint_structure,
)
from .energy_collocation import EnergyPreservingCollocation as EnergyPreservingCollocation
from .gonzalez_r import GonzalezR as GonzalezR
from .gonzalez_f import GonzalezF as GonzalezF
from .idla import IDLA as IDLA
from .projection import Projection as Projection, ProjectionState as ProjectionState
from .sidla import SIDLA as SIDLA
from .spark import (
    LOBATTO_IIIA_B_2 as LOBATTO_IIIA_B_2,
    LOBATTO_IIIA_B_C_CSTAR_D_2 as LOBATTO_IIIA_B_C_CSTAR_D_2,
    lobatto_spark_tableau as lobatto_spark_tableau,
    SPARK as SPARK,
    SPARKTableau as SPARKTableau,
)
