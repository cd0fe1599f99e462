"""The paper's systems: each example bundles its parameters (`.args`), its reduced
equations in adapted coordinates (`.adapted`, a `SkewGradientSystem`), its constraint
matrix and frame, maps between (q, p) and adapted coordinates, and initial-state
helpers. Beside them Euler's disk (`rolling_disk_3d`), a system as a mechanician
derives it, given only in canonical and Lagrangian form."""

from .._adapted import discrete_constraint_residual as discrete_constraint_residual
from ._chaotic_quartic import chaotic_quartic as chaotic_quartic, ChaoticQuartic as ChaoticQuartic
from ._contact_oscillator import contact_oscillator as contact_oscillator, ContactOscillator as ContactOscillator
from ._chaplygin_sleigh import chaplygin_sleigh as chaplygin_sleigh, ChaplyginSleigh as ChaplyginSleigh
from ._rolling_disk import rolling_disk as rolling_disk, RollingDisk as RollingDisk
from ._rolling_disk_3d import rolling_disk_3d as rolling_disk_3d, RollingDisk3D as RollingDisk3D
from ._suslov import suslov as suslov, Suslov as Suslov
from ._gearbox import gearbox as gearbox, Gearbox as Gearbox
