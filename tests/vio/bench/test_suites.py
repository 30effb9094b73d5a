"""Benchmark suites as YAML data files: the packaged ones keep the cases and methods they had in Python, and a
bad suite file is one clear line."""

from __future__ import annotations

import itertools

import pytest

from vio.bench.suites import (
    EUROC_GT_FILE,
    FIXED_LAG,
    IMU_ONLY,
    MODEL,
    MODEL_POSITIONS,
    MODEL_SEEDS,
    PARTS,
    SUITES,
    VIO,
    VIO_AND_BATCH,
    VISION_ONLY,
    Case,
    get_suite,
    load_suite,
)
from vio.errors import ConfigError


def _grid(scenarios, imus, seeds, duration_s, images=True):
    return tuple(Case(s, seed, imu, duration_s, images) for s, imu, seed in itertools.product(scenarios, imus, seeds))


def _python_suites() -> dict:
    """The suites as `vio/bench/suites.py` defined them in code before issue 19 (cases, methods, plots)."""
    drift = (IMU_ONLY, VIO_AND_BATCH, VISION_ONLY, FIXED_LAG)
    full = _grid(["orbit", "figure8", "room"], ["phone", "tactical"], [0, 1, 2, 3, 4], 60.0)
    if EUROC_GT_FILE.exists():
        full += _grid([str(EUROC_GT_FILE)], ["phone"], [0, 1, 2], 60.0)
    quick = _grid(["orbit", "figure8", "room"], ["phone"], [0], 15.0)
    quick += (Case("orbit", 1, "phone", 15.0), Case("orbit", 0, "tactical", 15.0))
    return {
        "tiny": ((Case("orbit", 0, "phone", 4.0),), (IMU_ONLY, VIO), True),
        "quick": (quick, drift, True),
        "full": (full, drift, True),
        "drift60": (
            _grid(["orbit", "figure8", "room"], ["phone", "tactical", "ideal"], [0, 1, 2], 60.0, False),
            (IMU_ONLY,),
            True,
        ),  # fmt: skip
        "model": (
            tuple(Case("orbit", s, "phone", 60.0, stills_hz=2.0) for s in MODEL_SEEDS),
            (MODEL, MODEL_POSITIONS),
            False,
        ),  # fmt: skip
        "parts": (tuple(Case("orbit", 101, "phone", 60.0, part=p, stills_hz=2.0) for p in PARTS), (MODEL,), False),
    }


@pytest.mark.parametrize("name", [s for s in SUITES if s not in ("scale", "scale60", "model_guided")])
def test_packaged_suites_keep_their_cases_and_methods(name):
    cases, methods, plots = _python_suites()[name]
    suite = get_suite(name)
    assert suite.name == name and suite.cases == cases and suite.methods == methods and suite.plots == plots


def test_scale_suite_uses_held_out_seeds():
    scale = get_suite("scale")
    assert len(scale.cases) == 21 and {c.seed for c in scale.cases} == set(range(301, 308))
    assert {c.scenario for c in scale.cases} == {"orbit", "figure8", "room"} and scale.methods == (VIO_AND_BATCH,)


def test_scale60_suite_pairs_each_seed_with_and_without_the_phases():
    cases = get_suite("scale60").cases
    plain = [c for c in cases if not c.phases]
    phased = [c for c in cases if c.phases]
    assert [c.seed for c in plain] == [c.seed for c in phased] == list(range(311, 321))
    assert phased[0].phases == {"still_start_s": 3.0, "excite_s": 5.0, "still_end_s": 3.0}
    assert all(c.scenario == "orbit" and c.duration_s == 60.0 and c.imu == "phone" for c in cases)
    assert phased[0].key == "orbit_phone_s311_60s_still3+3s_excite5s" and plain[0].key == "orbit_phone_s311_60s"
    assert phased[0].label == "orbit (still 3+3 s, excite 5 s)" and plain[0].label == "orbit"  # tabulated apart
    assert len({c.key for c in cases}) == 20


def test_model_method_fields_survive_yaml():
    model = get_suite("model")
    assert [m.positions_sigma_m for m in model.methods] == [0.0, 1e-4]
    assert all(isinstance(c.stills_hz, float) and c.stills_hz == 2.0 for c in model.cases)
    assert [c.part for c in get_suite("parts").cases] == list(PARTS)


def test_a_suite_file_by_path(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text(
        "name: mine\nmethods:\n  - {name: lag, kind: vio, presets: [fixed_lag], overrides: ['run.refine=false']}\n"
        "cases:\n  - grid: {imu: [phone, tactical], seed: [7, 8]}\n    scenario: room\n    duration_s: 5\n"
    )
    suite = get_suite(str(path))
    assert suite.name == "mine" and suite.methods[0].presets == ("fixed_lag",)
    assert [(c.imu, c.seed) for c in suite.cases] == [("phone", 7), ("phone", 8), ("tactical", 7), ("tactical", 8)]
    assert suite.cases[0].duration_s == 5.0 and isinstance(suite.cases[0].duration_s, float)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("name: x\nmethods: [{name: a, kind: vio}]\ncases: [{scenario: orbit, seed: 0, imu: phone}]\n", "needs"),
        ("name: x\nmethods: [{name: a, kind: vio, colour: red}]\ncases: []\n", "needs a non-empty"),
        ("name: x\nmethods: [{name: a, kind: vio, colour: red}]\ncases: [{seed: 1}]\n", "unknown method field"),
        (
            "name: x\nmethods: [{name: a, kind: vio}]\ncases: [{scenario: orbit, seed: one, imu: p, duration_s: 1}]\n",
            "seed must be int",
        ),  # fmt: skip
        ("name: x\nmethods: [{name: a, kind: vio}]\ncases: [{grid: {sead: [1]}}]\n", "unknown case field"),
        ("name: x\nmethod: []\n", "unknown suite key"),
        ("name: [x\n", "not valid YAML"),
        (
            "name: x\nmethods: [{name: a, kind: model, model_args: --no-visibility}]\ncases: [{seed: 1}]\n",
            "list of str",
        ),
    ],
)
def test_a_bad_suite_file_is_one_line(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        load_suite(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_model_args_reach_the_method_and_survive_its_dict_form(tmp_path):
    import dataclasses

    from vio.bench.suites import method_from_dict

    path = tmp_path / "m.yaml"
    path.write_text(
        "name: m\nmethods: [{name: mv, kind: model, model_args: [--no-visibility]}]\n"
        "cases: [{scenario: orbit, seed: 1, imu: phone, duration_s: 1}]\n"
    )
    method = load_suite(path).methods[0]
    assert method.model_args == ("--no-visibility",)
    as_json = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(method).items()}
    assert method_from_dict(as_json) == method


def test_model_guided_suite_films_the_model_seeds_with_the_capture_advice():
    guided = get_suite("model_guided")
    plain = get_suite("model")
    assert [c.seed for c in guided.cases] == [c.seed for c in plain.cases] == MODEL_SEEDS
    assert all(c.phases == {"still_start_s": 3.0, "excite_s": 5.0, "still_end_s": 3.0} for c in guided.cases)
    assert all(c.stills_hz == 2.0 and c.duration_s == 60.0 and c.imu == "phone" for c in guided.cases)
    assert guided.methods == (MODEL,) and not guided.plots


def test_unknown_suite_names_the_known_ones():
    known = "drift60, full, model, model_guided, parts, quick, scale, scale60"
    with pytest.raises(ConfigError, match=f"unknown benchmark suite 'nope'; known: {known}"):
        get_suite("nope")


def test_the_bench_worker_simulates_a_case_with_its_phases(tmp_path):
    """The worker's simulate task passes the case's phases on (IMU and ground truth only, a 1 s orbit)."""
    import dataclasses
    import json

    import yaml

    from vio.bench.worker import main as worker_main

    case = Case("orbit", 311, "ideal", 1.0, images=False, still_start_s=1.0, excite_s=2.0)
    task = tmp_path / "task" / "task.json"
    task.parent.mkdir()
    capture = tmp_path / "cap"
    task.write_text(json.dumps({"kind": "simulate", "case": dataclasses.asdict(case), "capture": str(capture)}))
    assert worker_main(str(task)) == 0
    result = json.loads((task.parent / "result.json").read_text())
    assert "error" not in result, result
    phases = yaml.safe_load((capture / "scene" / "scene.yaml").read_text())["phases"]
    assert phases["still_start_s"] == 1.0 and phases["excite_s"] == 2.0 and phases["motion_s"] == 1.0
