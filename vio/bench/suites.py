"""Benchmark suites: which captures (scenario x IMU grade x seed x duration) and which methods to run.

A *case* is one simulated capture; a *method* is one way of estimating the trajectory from it. Methods are
named rows of `results.json`: `imu_only` (the thesis's dead reckoning), `vio` (the online estimator as shipped),
`batch` (full Levenberg-Marquardt over the same graph, the optimum), `vision_only` (the same frontend and graph
without IMU factors, scored after Sim3 alignment because its scale is unknown), and variants of `vio` given as
named presets or `--set`-style config overrides (for example the fixed-lag smoother).

Suites are data: `vio/bench/suite_files/NAME.yaml` (packaged), or any YAML file of the same form given by path:

    name: quick
    notes: free text
    plots: true                     # optional, default true
    methods:                        # Method fields
      - {name: vio, kind: vio, refine: true, presets: [fixed_lag], overrides: ["smoother.lag_s=3"]}
    cases:                          # Case fields; `grid` lists values whose product makes cases
      - {scenario: orbit, seed: 1, imu: phone, duration_s: 15.0}
      - grid: {scenario: [orbit, room], imu: [phone], seed: [0, 1]}
        duration_s: 15.0
        if_exists: true             # skip when `scenario` names a file that is absent
A grid's cases come in the order scenario, imu, seed, then any other field (the last varies fastest).
`{shared}` in a scenario is the project's `../shared` folder.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from vio.errors import ConfigError

SUITE_DIR = Path(__file__).resolve().parent / "suite_files"
# the packaged suites
SUITES = ("tiny", "quick", "full", "drift60", "model", "model_guided", "parts", "scale", "scale60")
PARTS = ("cube", "cube_features", "freeform")
ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared"
# A real drone trajectory (EuRoC V1_01 ground truth) driving the simulator: "trajectories from files".
EUROC_GT_FILE = SHARED / "data" / "euroc_v1_01" / "mav0" / "state_groundtruth_estimate0" / "data.csv"


@dataclass(frozen=True)
class Case:
    scenario: str  # orbit | figure8 | room | a trajectory file path
    seed: int
    imu: str  # phone | tactical | ideal
    duration_s: float  # the scenario's motion, s (the capture's length without the phases below)
    images: bool = True  # render the camera (False: IMU and ground truth only, for IMU-only suites)
    part: str = "cube"  # the part on the table (vio.sim.parts: cube, cube_features, freeform)
    stills_hz: float = 0.0  # full-resolution stills stream (cam1) for the part model; 0: none
    still_start_s: float = 0.0  # capture phases (vio.sim.phases): held still before the motion, s
    excite_s: float = 0.0  # then shaken in all directions, s
    still_end_s: float = 0.0  # held still after it, s

    @property
    def phases(self) -> dict[str, float]:
        """`vio.sim.api.simulate`'s phase lengths when any is set, else {}."""
        p = (self.still_start_s, self.excite_s, self.still_end_s)
        return dict(zip(("still_start_s", "excite_s", "still_end_s"), p, strict=True)) if any(p) else {}

    @property
    def key(self) -> str:
        """File-system name of the cached capture (scenario files are named by their stem)."""
        name = Path(self.scenario).stem if ("/" in self.scenario or "." in self.scenario) else self.scenario
        key = f"{name}_{self.imu}_s{self.seed}_{self.duration_s:g}s" + ("" if self.images else "_noimg")
        if self.part != "cube":
            key += f"_{self.part}"
        key += f"_stills{self.stills_hz:g}hz" if self.stills_hz > 0 else ""
        if self.phases:
            key += f"_still{self.still_start_s:g}+{self.still_end_s:g}s_excite{self.excite_s:g}s"
        return key

    @property
    def label(self) -> str:
        """Scenario name as shown in tables, with the capture phases when there are any (so a suite's captures
        with and without them are tabulated and paired apart)."""
        name = Path(self.scenario).stem if "/" in self.scenario else self.scenario
        if self.phases:
            name += f" (still {self.still_start_s:g}+{self.still_end_s:g} s, excite {self.excite_s:g} s)"
        return name


@dataclass(frozen=True)
class Method:
    name: str  # the `method` column of results.json
    kind: str  # imu_only | vio (vio also yields `batch` when refine is on) | vision_only | model
    presets: tuple[str, ...] = ()  # named config presets (vio/presets/NAME.yaml), applied first
    overrides: tuple[str, ...] = ()  # `section.key=value` config overrides, applied after the presets
    refine: bool = False  # also produce the batch optimum (row `batch`) from the same run
    positions_sigma_m: float = 0.0  # model: anchor the run to known positions (ground truth + this noise); 0: none
    model_args: tuple[str, ...] = ()  # model: extra `vio model` arguments, e.g. ("--no-visibility",)


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
FIXED_LAG = Method("vio_fixed_lag", "vio", presets=("fixed_lag",))
# The part chain (run, model, measure, compare); with positions: known body positions at 2 Hz, 0.1 mm per axis.
MODEL = Method("model", "model")
MODEL_POSITIONS = Method("model_positions", "model", positions_sigma_m=1e-4)
MODEL_SEEDS = [101, 102, 103, 104, 105]  # seeds no test uses (suite_files/model.yaml lists them too)

CASE_FIELDS = {f.name: f.type for f in fields(Case)}
METHOD_FIELDS = {f.name for f in fields(Method)}
GRID_ORDER = ("scenario", "imu", "seed", "duration_s", "part", "stills_hz", "still_start_s", "excite_s",
              "still_end_s", "images")  # fmt: skip
_TYPES: dict[str, type] = {"scenario": str, "seed": int, "imu": str, "duration_s": float, "images": bool,
                           "part": str, "stills_hz": float, "still_start_s": float, "excite_s": float,
                           "still_end_s": float}  # fmt: skip


def _value(where: str, key: str, v: Any) -> Any:
    want = _TYPES[key]
    if want is float and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if not isinstance(v, want) or (want is int and isinstance(v, bool)):
        raise ConfigError(f"{where}: {key} must be {want.__name__}, got {v!r}")
    return v.replace("{shared}", str(SHARED)) if key == "scenario" else v


def _cases(where: str, entry: Any) -> list[Case]:
    if not isinstance(entry, dict):
        raise ConfigError(f"{where}: a case must be a mapping, got {entry!r}")
    unknown = set(entry) - set(CASE_FIELDS) - {"grid", "if_exists"}
    grid = entry.get("grid") or {}
    if not isinstance(grid, dict):
        raise ConfigError(f"{where}: grid must be a mapping of field: [values]")
    unknown |= set(grid) - set(CASE_FIELDS)
    if unknown:
        raise ConfigError(
            f"{where}: unknown case field(s) {', '.join(sorted(unknown))}; known: {', '.join(CASE_FIELDS)}"
        )
    both = set(grid) & set(entry)
    if both:
        raise ConfigError(f"{where}: {', '.join(sorted(both))} given both in grid and as a single value")
    fixed = {k: _value(where, k, v) for k, v in entry.items() if k in CASE_FIELDS}
    axes = [k for k in GRID_ORDER if k in grid]
    values = []
    for k in axes:
        vs = grid[k] if isinstance(grid[k], list) else [grid[k]]
        values.append([_value(where, k, v) for v in vs])
    missing = {"scenario", "seed", "imu", "duration_s"} - set(fixed) - set(axes)
    if missing:
        raise ConfigError(f"{where}: a case needs {', '.join(sorted(missing))}")
    cases = [Case(**fixed, **dict(zip(axes, combo, strict=True))) for combo in itertools.product(*values)]
    if entry.get("if_exists"):
        cases = [c for c in cases if Path(c.scenario).exists()]
    return cases


def method_from_dict(d: dict[str, Any]) -> Method:
    """A Method back from its dict form (JSON turns its tuples into lists)."""
    return Method(**{**d, **{k: tuple(d.get(k, ())) for k in ("presets", "overrides", "model_args")}})


def _method(where: str, entry: Any) -> Method:
    if not isinstance(entry, dict) or "name" not in entry or "kind" not in entry:
        raise ConfigError(f"{where}: a method must be a mapping with at least name and kind, got {entry!r}")
    unknown = set(entry) - METHOD_FIELDS
    if unknown:
        raise ConfigError(f"{where}: unknown method field(s) {', '.join(sorted(unknown))}; known: "
                          f"{', '.join(sorted(METHOD_FIELDS))}")  # fmt: skip
    fixed = dict(entry)
    for k in ("presets", "overrides", "model_args"):
        if not isinstance(fixed.get(k, []), list) or not all(isinstance(s, str) for s in fixed.get(k, [])):
            raise ConfigError(f"{where}: {k} must be a list of strings")
        fixed[k] = tuple(fixed.get(k, ()))
    if "positions_sigma_m" in fixed:
        fixed["positions_sigma_m"] = float(fixed["positions_sigma_m"])
    return Method(**fixed)


def load_suite(path: str | Path) -> Suite:
    """A suite from a YAML file (the form in this module's docstring); one-line ConfigError for a bad file."""
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the suite: {exc.strerror or exc}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a suite must be a mapping with name, methods and cases")
    unknown = set(data) - {"name", "notes", "plots", "methods", "cases"}
    if unknown:
        raise ConfigError(f"{path}: unknown suite key(s) {', '.join(sorted(unknown))}")
    if not data.get("methods") or not data.get("cases"):
        raise ConfigError(f"{path}: a suite needs a non-empty methods list and cases list")
    methods = tuple(_method(f"{path}: methods[{i}]", m) for i, m in enumerate(data["methods"]))
    names = [m.name for m in methods]
    if len(set(names)) != len(names):
        raise ConfigError(f"{path}: method names must be unique, got {names}")
    cases = tuple(c for i, e in enumerate(data["cases"]) for c in _cases(f"{path}: cases[{i}]", e))
    if len({c.key for c in cases}) != len(cases):
        raise ConfigError(f"{path}: two cases describe the same capture")
    return Suite(str(data.get("name") or path.stem), cases, methods, str(data.get("notes") or ""),
                 bool(data.get("plots", True)))  # fmt: skip


def get_suite(name: str) -> Suite:
    """A packaged suite by name, or a suite file by path. Packaged: `tiny` (tests), `quick` (under 15 min on 2
    cores), `full` (the Monte-Carlo run), `drift60` (the IMU-only baseline alone on 60 s captures without images:
    the thesis's failure, in a minute), `model` (the cube's part model over 5 seeds, with and without known
    positions), `parts` (the three parts, the study's Table 2) and `scale` (scale error against the run's stated
    sigma over 5 held-out seeds)."""
    if name.endswith((".yaml", ".yml")) or "/" in name:
        return load_suite(name)
    path = SUITE_DIR / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in SUITE_DIR.glob("*.yaml"))
        raise ConfigError(f"unknown benchmark suite {name!r}; known: {', '.join(known)}, or a path to a YAML file")
    return load_suite(path)
