"""The systems nhjax ships, each an `AbstractExample`: its parameters (`.args`), the forms
it comes in (canonical, from its Lagrangian, reduced in adapted coordinates), maps
between them and initial states in one convention. `EXAMPLES` is the catalogue, by the
names the command line uses: the paper's systems, Euler's disk (`rolling_disk_3d`), a
system as a mechanician derives it, a differential-drive robot with motors and
friction (`differential_drive`), and a tractor pulling any number of trailers
(`tractor_trailers`), a family of real systems of any size."""

from .._adapted import discrete_constraint_residual as discrete_constraint_residual
from ._example import AbstractExample as AbstractExample
from ._chaotic_quartic import chaotic_quartic as chaotic_quartic, ChaoticQuartic as ChaoticQuartic
from ._contact_oscillator import contact_oscillator as contact_oscillator, ContactOscillator as ContactOscillator
from ._chaplygin_sleigh import chaplygin_sleigh as chaplygin_sleigh, ChaplyginSleigh as ChaplyginSleigh
from ._rolling_disk import rolling_disk as rolling_disk, RollingDisk as RollingDisk
from ._rolling_disk_3d import rolling_disk_3d as rolling_disk_3d, RollingDisk3D as RollingDisk3D
from ._suslov import suslov as suslov, Suslov as Suslov
from ._gearbox import gearbox as gearbox, Gearbox as Gearbox
from ._differential_drive import (
    differential_drive as differential_drive,
    DifferentialDrive as DifferentialDrive,
    torque_at as torque_at,
)
from ._tractor_trailers import tractor_trailers as tractor_trailers, TractorTrailers as TractorTrailers

# Every example by its name; each is made with its default parameters by calling its class.
EXAMPLES: dict[str, type[AbstractExample]] = {
    example.name: example
    for example in (
        Gearbox,
        ChaoticQuartic,
        ChaplyginSleigh,
        RollingDisk,
        Suslov,
        ContactOscillator,
        RollingDisk3D,
        DifferentialDrive,
        TractorTrailers,
    )
}
