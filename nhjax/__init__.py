"""nhjax: energy- and constraint-preserving integrators for nonholonomic systems.

x64 is not switched on here: call `jax.config.update("jax_enable_x64", True)` (or set
`JAX_ENABLE_X64=1`) before creating arrays to get float64, the normal mode for energy
conservation to roundoff. float32 works too, with tolerances that follow the dtype.
"""

from . import examples as examples
from ._discrete_gradient import avf as avf, gonzalez as gonzalez, itoh_abe as itoh_abe
from ._ensemble import integrate_ensemble as integrate_ensemble
from ._integrate import integrate as integrate
from ._integrate_adaptive import integrate_adaptive as integrate_adaptive
from ._nonholonomic import NonholonomicSystem as NonholonomicSystem
from ._results import RESULTS as RESULTS
from ._runner import run_chunked as run_chunked
from ._solution import Solution as Solution
from ._solver import (
    AbstractMethod as AbstractMethod,
    averaged_structure as averaged_structure,
    Composition as Composition,
    COMPOSITION_SCHEMES as COMPOSITION_SCHEMES,
    DiscreteGradient as DiscreteGradient,
    EnergyPreservingCollocation as EnergyPreservingCollocation,
    GonzalezF as GonzalezF,
    GonzalezR as GonzalezR,
    IDLA as IDLA,
    LOBATTO_IIIA_B_2 as LOBATTO_IIIA_B_2,
    LOBATTO_IIIA_B_C_CSTAR_D_2 as LOBATTO_IIIA_B_C_CSTAR_D_2,
    lobatto_spark_tableau as lobatto_spark_tableau,
    midpoint_structure as midpoint_structure,
    Projection as Projection,
    SIDLA as SIDLA,
    SPARK as SPARK,
    SPARKTableau as SPARKTableau,
)
from ._system import AbstractSystem as AbstractSystem, SkewGradientSystem as SkewGradientSystem


__version__ = "0.1.0"
