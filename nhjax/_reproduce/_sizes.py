"""How big each experiment is: the paper's sizes (`FULL`) and a reduced set that runs in a
few minutes (`QUICK`)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class Sizes:
    """Every size and setting the experiments take from outside.

    - `seed`: the key for the random initial states (Figures 1 and 3).
    - `quartic_methods`: the methods of Figure 1, by name (see `_common.METHODS`).
    - `order_step_sizes`: Figure 1(a)'s step sizes, each dividing t = 10.
    - `ensemble_count`, `ensemble_t1`, `ensemble_save_every`, `ensemble_chunk_steps`:
        Figure 1(d)'s batch of states, run at h = 0.1 to `ensemble_t1`.
    - `sleigh_steps`, `sleigh_gonzalez_r`: Figure 2's steps of h = 0.5, and whether
        GONZALEZ-R on the canonical sleigh runs beside the adapted method.
    - `gearbox_steps`, `gearbox_save_every`, `gearbox_chunk_steps`: Figure 3 at h = 0.1.
    - `work_methods`, `work_step_sizes`, `work_tolerances`, `work_repeats`: Figure 4's
        fixed-step methods and their step sizes, Dopri8's tolerances, and how many timed
        runs the median is taken over.
    - `work_compositions`, `work_composition_step_sizes`: Figure 4's compositions of
        order 4, 6 and 8 (see `_common.COMPOSITIONS`) and their step sizes.
    - `work_targets`: the solution errors at which Figure 4 names the cheapest runs.
    - `contact_steps`, `contact_save_every`: Figure 5's steps of h = 0.1 on the contact
        oscillator, and the saving interval.
    """

    seed: int
    quartic_methods: tuple[str, ...]
    order_step_sizes: tuple[float, ...]
    ensemble_count: int
    ensemble_t1: float
    ensemble_save_every: int
    ensemble_chunk_steps: int
    sleigh_steps: int
    sleigh_gonzalez_r: bool
    gearbox_steps: int
    gearbox_save_every: int
    gearbox_chunk_steps: int
    work_methods: tuple[str, ...]
    work_step_sizes: tuple[float, ...]
    work_tolerances: tuple[float, ...]
    work_repeats: int
    work_compositions: tuple[str, ...]
    work_composition_step_sizes: tuple[float, ...]
    work_targets: tuple[float, ...]
    contact_steps: int
    contact_save_every: int


FULL = Sizes(
    seed=2016,
    quartic_methods=("SI-DLA", "I-DLA", "SPARK", "AVF", "GONZALEZ"),
    order_step_sizes=(0.2, 0.1, 0.05, 0.025, 0.0125, 0.00625),
    # Figure 1(d): 200 states to t = 2000 at h = 0.1, 501 saves.
    ensemble_count=200,
    ensemble_t1=2000.0,
    ensemble_save_every=40,
    ensemble_chunk_steps=2000,
    sleigh_steps=2000,
    sleigh_gonzalez_r=True,
    # Figure 3: t in [0, 50000] at h = 0.1.
    gearbox_steps=500_000,
    gearbox_save_every=100,
    gearbox_chunk_steps=50_000,
    work_methods=("GONZALEZ-R", "GONZALEZ-F", "SI-DLA", "I-DLA", "SPARK", "AVF", "GONZALEZ", "Tsit5"),
    # GONZALEZ-F's root find stalls at its tolerance (64 eps) on the quartic at h = 0.00625.
    work_step_sizes=(0.2, 0.1, 0.05, 0.025, 0.0125),
    work_tolerances=(1e-4, 1e-6, 1e-8, 1e-10, 1e-12),
    work_repeats=5,
    work_compositions=(
        "GONZALEZ-R order 4", "GONZALEZ-R order 6", "GONZALEZ-R order 8",
        "GONZALEZ order 4", "GONZALEZ order 6", "GONZALEZ order 8",
    ),
    work_composition_step_sizes=(0.5, 0.25, 0.2, 0.125, 0.1, 0.0625, 0.05, 0.025),
    work_targets=(1e-3, 1e-6, 1e-9),
    # Figure 5: t in [0, 10000].
    contact_steps=100_000,
    contact_save_every=100,
)

# Compilation, not stepping, is most of a quick run: the same programs as FULL, shorter
# long runs.
QUICK = dataclasses.replace(
    FULL,
    # Figure 1(d)'s slopes are statistics of the batch: from 50 states SI-DLA's ranged
    # from 0.27 to 0.76 of the line between builds that round differently, across the
    # criterion's edge; the paper's 200 states, to a shorter time, are kept.
    ensemble_count=200,
    ensemble_t1=500.0,
    ensemble_save_every=10,
    ensemble_chunk_steps=1000,
    # GONZALEZ-R on the sleigh alone compiles for longer than the rest of Figure 2.
    sleigh_gonzalez_r=False,
    gearbox_steps=50_000,
    gearbox_chunk_steps=10_000,
    work_repeats=3,
    contact_steps=20_000,
)
