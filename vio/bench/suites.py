"""Benchmark suites: which captures (scenario x IMU grade x seed x duration) and which methods to run.

A *case* is one simulated capture; a *method* is one way of estimating the trajectory from it. Methods are
named rows of `results.json`: `imu_only` (the thesis's dead reckoning), `vio` (the online estimator as shipped),
`batch` (full Levenberg-Marquardt over the same graph, the optimum), `vision_only` (the same frontend and graph
without IMU factors, scored after Sim3 alignment because its scale is unknown), and variants of `vio` given as
`--set`-style config overrides (for example the fixed-lag smoother).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

from vio.errors import ConfigError

SUITES = ("tiny", "quick", "full", "drift60", "model", "parts")
PARTS = ("cube", "cube_features", "freeform")
ROOT = Path(__file__).resolve().parents[2]
# A real drone trajectory (EuRoC V1_01 ground truth) driving the simulator: "trajectories from files".
EUROC_GT_FILE = ROOT.parent / "shared" / "data" / "euroc_v1_01" / "mav0" / "state_groundtruth_estimate0" / "data.csv"


@dataclass(frozen=True)
class Case:
    scenario: str  # orbit | figure8 | room | a trajectory file path
    seed: int
    imu: str  # phone | tactical | ideal
    duration_s: float  # capture length, s
    images: bool = True  # render the camera (False: IMU and ground truth only, for IMU-only suites)
    part: str = "cube"  # the part on the table (vio.sim.parts: cube, cube_features, freeform)
    stills_hz: float = 0.0  # full-resolution stills stream (cam1) for the part model; 0: none

    @property
    def key(self) -> str:
        """File-system name of the cached capture (scenario files are named by their stem)."""
        name = Path(self.scenario).stem if ("/" in self.scenario or "." in self.scenario) else self.scenario
        key = f"{name}_{self.imu}_s{self.seed}_{self.duration_s:g}s" + ("" if self.images else "_noimg")
        if self.part != "cube":
            key += f"_{self.part}"
        return key + (f"_stills{self.stills_hz:g}hz" if self.stills_hz > 0 else "")

    @property
    def label(self) -> str:
        """Scenario name as shown in tables."""
        return Path(self.scenario).stem if "/" in self.scenario else self.scenario


@dataclass(frozen=True)
class Method:
    name: str  # the `method` column of results.json
    kind: str  # imu_only | vio (vio also yields `batch` when refine is on) | vision_only
    presets: tuple[str, ...] = ()  # named config presets (vio/presets/NAME.yaml), applied first
    overrides: tuple[str, ...] = ()  # `section.key=value` config overrides, applied after the presets
    refine: bool = False  # also produce the batch optimum (row `batch`) from the same run
    positions_sigma_m: float = 0.0  # model: anchor the run to known positions (ground truth + this noise); 0: none


@dataclass(frozen=True)
class Suite:
    name: str
    cases: tuple[Case, ...]
    methods: tuple[Method, ...]
    notes: str = ""
    plots: bool = field(default=True)


IMU_ONLY = Method("imu_only", "imu_only")
VIO_AND_BATCH = Method("vio", "vio", refine=True)
VIO = Method("vio", "vio")
VISION_ONLY = Method("vision_only", "vision_only", presets=("vision_only",))
FIXED_LAG = Method("vio_lag3s", "vio", presets=("fixed_lag",))
# The part chain (run, model, measure, compare); with positions: known body positions at 2 Hz, 0.1 mm per axis.
MODEL = Method("model", "model")
MODEL_POSITIONS = Method("model_positions", "model", positions_sigma_m=1e-4)
MODEL_SEEDS = [101, 102, 103, 104, 105]  # seeds no test uses


def _grid(
    scenarios: list[str], imus: list[str], seeds: list[int], duration_s: float, images: bool = True
) -> tuple[Case, ...]:
    return tuple(Case(s, seed, imu, duration_s, images) for s, imu, seed in itertools.product(scenarios, imus, seeds))


def get_suite(name: str) -> Suite:
    """The named suite: `tiny` (tests), `quick` (under 15 min on 2 cores), `full` (the Monte-Carlo run),
    `drift60` (the IMU-only baseline alone on 60 s captures without images: the thesis's failure, in a minute),
    `model` (the cube's part model over 5 seeds, with and without known positions) and `parts` (the three
    parts, the study's Table 2)."""
    if name == "tiny":
        return Suite("tiny", (Case("orbit", 0, "phone", 4.0),), (IMU_ONLY, VIO), "test-only", plots=True)
    if name == "quick":
        cases = _grid(["orbit", "figure8", "room"], ["phone"], [0], 15.0)
        cases += (Case("orbit", 1, "phone", 15.0), Case("orbit", 0, "tactical", 15.0))
        return Suite("quick", cases, (IMU_ONLY, VIO_AND_BATCH, VISION_ONLY, FIXED_LAG), "5 captures of 15 s")
    if name == "full":
        cases = _grid(["orbit", "figure8", "room"], ["phone", "tactical"], [0, 1, 2, 3, 4], 60.0)
        if EUROC_GT_FILE.exists():
            cases += _grid([str(EUROC_GT_FILE)], ["phone"], [0, 1, 2], 60.0)
        return Suite("full", cases, (IMU_ONLY, VIO_AND_BATCH, VISION_ONLY, FIXED_LAG), "30-33 captures of 60 s")
    if name == "drift60":
        cases = _grid(["orbit", "figure8", "room"], ["phone", "tactical", "ideal"], [0, 1, 2], 60.0, images=False)
        return Suite("drift60", cases, (IMU_ONLY,), "27 IMU-only captures of 60 s")
    if name == "model":
        cases = tuple(Case("orbit", s, "phone", 60.0, stills_hz=2.0) for s in MODEL_SEEDS)
        return Suite("model", cases, (MODEL, MODEL_POSITIONS), "the cube from 5 captures of 60 s", plots=False)
    if name == "parts":
        cases = tuple(Case("orbit", 101, "phone", 60.0, part=p, stills_hz=2.0) for p in PARTS)
        return Suite("parts", cases, (MODEL,), "the three parts from 60 s captures (seed 101)", plots=False)
    raise ConfigError(f"unknown benchmark suite {name!r}; known: {', '.join(SUITES)}")
